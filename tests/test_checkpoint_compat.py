"""nerfstudio 1.1.5 checkpoints hold numpy scalars; torch >= 2.6 refuses them unless the plugin is imported."""

import pickle
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

SAVE_AND_LOAD = textwrap.dedent(
    """
    import sys, numpy as np, torch
    if sys.argv[2] == "plugin":
        import frugalnerf_ns  # noqa: F401
    payload = {"step": 3, "scheduler": {"base_lrs": [np.float64(0.08)], "dtype": np.dtype("float32")}}
    if sys.argv[3] == "evil":
        import fractions
        payload["evil"] = fractions.Fraction(1, 3)  # an arbitrary global must stay forbidden
    torch.save(payload, sys.argv[1])
    loaded = torch.load(sys.argv[1])  # weights_only=True is the default since torch 2.6
    print("loaded", float(loaded["scheduler"]["base_lrs"][0]))
    """
)


def _run(tmp_path, mode, content="numpy"):
    return subprocess.run(
        [sys.executable, "-c", SAVE_AND_LOAD, str(tmp_path / f"{mode}-{content}.ckpt"), mode, content],
        capture_output=True,
        text=True,
    )


def test_plain_torch_refuses_numpy_scalars(tmp_path):
    # A fresh process: the plugin's allowance is process-wide, and this one has imported it.
    result = _run(tmp_path, "plain")
    assert result.returncode != 0
    assert "Unsupported global" in result.stderr and "numpy" in result.stderr


def _save_and_load(path, payload):
    """In this process, which imported the plugin (as every nerfstudio command that loads a run does)."""
    import frugalnerf_ns  # noqa: F401

    torch.save(payload, path)
    return torch.load(path)  # weights_only=True is the default since torch 2.6


def test_importing_the_plugin_allows_them(tmp_path):
    payload = {"step": 3, "scheduler": {"base_lrs": [np.float64(0.08)], "dtype": np.dtype("float32")}}
    loaded = _save_and_load(tmp_path / "plugin.ckpt", payload)
    assert float(loaded["scheduler"]["base_lrs"][0]) == 0.08 and loaded["scheduler"]["dtype"] == np.float32


def test_the_allowance_stays_narrow(tmp_path):
    import fractions

    payload = {"step": 3, "evil": fractions.Fraction(1, 3)}  # an arbitrary global must stay forbidden
    with pytest.raises(pickle.UnpicklingError, match="Unsupported global"):
        _save_and_load(tmp_path / "evil.ckpt", payload)
