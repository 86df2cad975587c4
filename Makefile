# The two commands a new user runs (README): `make demo` and `make test`. Each sets up ./.venv first
# when it is missing or was built from other pins.
VENV := .venv

.PHONY: setup demo test test-e2e test-slow lint benchmark gate

setup:
	@bash scripts/setup_venv.sh

demo: setup
	$(VENV)/bin/frugalnerf-demo

test: setup
	$(VENV)/bin/python -m pytest -q --durations=15

# End-to-end runs of the real tools (a tradeoff sweep on Ray, a failing sweep, every preset's evaluation during
# training, ...): CI runs them after `make test`.
test-e2e: setup
	$(VENV)/bin/python -m pytest -q --durations=15 -m e2e

# Pyflakes' checks (undefined names, unused imports), clean on the whole tree; CI runs it.
lint: setup
	$(VENV)/bin/ruff check .

test-slow: setup
	$(VENV)/bin/python -m pytest -q -m slow

benchmark: setup
	$(VENV)/bin/frugalnerf-bench vs-tensorf

# The quality gate (configs/gate.yaml): the CPU presets on fern, flower, horns, DTU scan65, the juice box and the
# bird against configs/gate_baseline.yaml; exits non-zero on a regression (10 runs, ~2 h on 2 cores; docs/development.md).
gate: setup
	$(VENV)/bin/frugalnerf-gate
