"""The distributions a FrugalNeRF run imports, pinned to this environment's versions: the wheelhouse's list.

A GPU node without internet gets the plugin from a folder of wheels (scripts/wheelhouse.sh). Installing
nerfstudio's whole dependency tree would bring open3d, jupyter, tensorboard and more (hundreds of MB) that
a training run never touches, so the list is measured instead of declared: a child process trains
``frugalnerf-tiny`` for a few steps on the procedural scene through ``ns-train``'s own entry point, imports
the modules that ``ns-eval``, ``ns-render`` and the viewer load, and reports ``sys.modules``; each module's
top-level package is mapped to the distribution that installed it.

Left out: torch, torchvision and everything torch itself requires (the node's own torch brings them, built
for its CUDA), this package (built as its own wheel), pip / setuptools / wheel, and transformers, which
torchmetrics imports only when it is installed (hidden from the traced run; the optional monocular depth
prior needs it).

With ``--node-freeze FILE`` (``pip list --format=freeze`` run on the node), distributions the node already
has are left out when its version satisfies every requirement that the listed distributions and this
package declare on them (so pip's resolver would accept it); an unpinned one is left out too.

Usage: python scripts/wheelhouse_requirements.py [--output requirements-wheelhouse.txt] [--node-freeze FILE]
"""

from __future__ import annotations

import argparse
import importlib.metadata as metadata
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, Iterable, List, Set

# What the child process runs: a real (tiny) training through ns-train's entry point, then the imports of the
# other commands a user runs on the node. ``--vis tensorboard``: with the viewer, ns-train waits for Ctrl-C
# after training; the viewer's modules are imported explicitly instead.
_CHILD = r"""
import importlib.abc, json, sys
from pathlib import Path
ABSENT = set(sys.argv[3].split(","))
class Absent(importlib.abc.MetaPathFinder):
    # Packages that are imported only when installed (torchmetrics' text metrics import transformers if present):
    # hide them, so the trace lists what a run needs, not what happens to be installed.
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in ABSENT:
            raise ModuleNotFoundError(f"No module named {name!r} (hidden by wheelhouse_requirements)")
        return None
sys.meta_path.insert(0, Absent())
import importlib.metadata as md
def _hidden(real):
    def lookup(name):
        if name.replace("_", "-").lower() in ABSENT:
            raise md.PackageNotFoundError(name)
        return real(name)
    return lookup
md.version, md.distribution = _hidden(md.version), _hidden(md.distribution)  # what RequirementCache asks
scene, out = Path(sys.argv[1]), Path(sys.argv[2])
from frugalnerf_ns.data.procedural_scene import write_procedural_scene
write_procedural_scene(scene)
sys.argv = ["ns-train", "frugalnerf-tiny", "--data", str(scene), "--output-dir", str(out), "--vis", "tensorboard",
            "--max-num-iterations", "3", "--machine.device-type", "cpu", "--viewer.quit-on-train-completion", "True"]
from nerfstudio.scripts import train
train.entrypoint()
import nerfstudio.scripts.eval, nerfstudio.scripts.render, nerfstudio.scripts.viewer.run_viewer
import nerfstudio.viewer.viewer, frugalnerf_ns.tools.offline_tools, frugalnerf_ns.scoring.lpips_offline
print("MODULES " + json.dumps(sorted(sys.modules)))
"""

ALWAYS_EXCLUDED = {"pip", "setuptools", "wheel", "frugalnerf-ns", "torch"}
# Built against one torch version, so it must be the node's own, like torch.
NODE_PROVIDED = {"torchvision"}
# Imported only when installed; hidden from the traced run (the optional monocular depth, [mono], needs it).
OPTIONAL_WHEN_ABSENT = ("transformers",)


def canonical(name: str) -> str:
    """PEP 503 normalised distribution name."""
    return re.sub(r"[-_.]+", "-", name).lower()


def imported_modules(workdir: Path) -> List[str]:
    """Module names loaded by a tiny training plus the imports of ns-eval, ns-render and the viewer."""
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(workdir / "scene"), str(workdir / "runs"), ",".join(OPTIONAL_WHEN_ABSENT)],
        capture_output=True, text=True,
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("MODULES ")]
    if proc.returncode != 0 or not lines:
        sys.exit(f"wheelhouse_requirements: the tiny training failed:\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("MODULES "):])


def distributions_of(modules: Iterable[str]) -> Set[str]:
    """Canonical names of the installed distributions that provide these modules' top-level packages."""
    providers = metadata.packages_distributions()
    found: Set[str] = set()
    for module in modules:
        for dist in providers.get(module.split(".")[0], []):
            found.add(canonical(dist))
    return found


def requirement_closure(root: str) -> Set[str]:
    """``root`` and every installed distribution it requires, transitively (extras and markers ignored)."""
    seen: Set[str] = set()
    todo = [canonical(root)]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue
        seen.add(name)
        for spec in requires:
            if "extra ==" in spec:
                continue
            todo.append(canonical(re.split(r"[\s;<>=!~\[(]", spec, maxsplit=1)[0]))
    return seen


def pinned_requirements(dists: Iterable[str]) -> Dict[str, str]:
    """name -> installed version, without torch's own closure and the always-excluded names."""
    excluded = requirement_closure("torch") | ALWAYS_EXCLUDED | NODE_PROVIDED
    pins: Dict[str, str] = {}
    for name in sorted(set(dists) - excluded):
        if name.startswith("nvidia-"):
            continue
        pins[name] = metadata.version(name)
    return pins


def declared_specifiers(dists: Iterable[str]) -> Dict[str, List[str]]:
    """name -> the version specifiers that ``dists`` and frugalnerf-ns require of it (markers ignored)."""
    from packaging.requirements import Requirement

    specs: Dict[str, List[str]] = {}
    for dist in [*dists, "frugalnerf-ns"]:
        try:
            requires = metadata.requires(dist) or []
        except metadata.PackageNotFoundError:
            continue
        for line in requires:
            requirement = Requirement(line)
            if requirement.marker is not None and "extra" in str(requirement.marker):
                continue
            specs.setdefault(canonical(requirement.name), []).append(str(requirement.specifier))
    return specs


def node_satisfied(pins: Dict[str, str], node_versions: Dict[str, str]) -> Set[str]:
    """Names in ``pins`` that the node has at a version every declared requirement on them accepts."""
    from packaging.specifiers import SpecifierSet
    from packaging.version import InvalidVersion, Version

    specs = declared_specifiers(pins)
    satisfied: Set[str] = set()
    for name in pins:
        if name not in node_versions:
            continue
        try:
            version = Version(node_versions[name])
        except InvalidVersion:
            continue
        if all(version in SpecifierSet(spec) for spec in specs.get(name, [])):
            satisfied.add(name)
    return satisfied


def read_freeze(path: Path) -> Dict[str, str]:
    """name -> version from ``pip list --format=freeze`` / ``pip freeze`` output (other lines ignored)."""
    versions: Dict[str, str] = {}
    for line in path.read_text().splitlines():
        if "==" in line and not line.startswith("#"):
            name, version = line.split("==", 1)
            versions[canonical(name.strip())] = version.strip()
    return versions


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output", type=Path, help="write name==version lines here (default: stdout)")
    parser.add_argument("--node-freeze", type=Path, help="the node's `pip list --format=freeze`: skip what it has")
    args = parser.parse_args()
    if args.node_freeze and not args.node_freeze.is_file():
        sys.exit(f"wheelhouse_requirements: --node-freeze {args.node_freeze}: no such file")
    with tempfile.TemporaryDirectory() as workdir:
        pins = pinned_requirements(distributions_of(imported_modules(Path(workdir))))
    if args.node_freeze:
        skipped = node_satisfied(pins, read_freeze(args.node_freeze))
        print(f"wheelhouse_requirements: the node already has {len(skipped)}: {' '.join(sorted(skipped))}", file=sys.stderr)
        pins = {name: version for name, version in pins.items() if name not in skipped}
    text = "".join(f"{name}=={version}\n" for name, version in pins.items())
    if args.output:
        args.output.write_text(text)
        print(f"wheelhouse_requirements: {len(pins)} distributions -> {args.output}", file=sys.stderr)
    else:
        sys.stdout.write(text)


if __name__ == "__main__":
    main()
