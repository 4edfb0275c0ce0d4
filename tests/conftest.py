"""Shared test set-up: PSF caches go to a per-session temporary folder, never the user's; the ``bmi`` fixture
runs the command line as a user does."""

import subprocess
import sys

import pytest

SUBPROCESS_PATIENCE_S = 1800.0
"""A safety net against a hung command only: a render on a cold PSF cache takes ~160 s alone and several times
that on a loaded 2-core machine, so no bound close to the idle run time belongs here."""


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    import os

    os.environ["BMI_CACHE_DIR"] = str(tmp_path_factory.mktemp("bmi_cache"))
    yield


@pytest.fixture(scope="session")
def passthrough_model(tmp_path_factory):
    """An ONNX model that follows the model_io contract and costs nothing: aif = the demosaiced input,
    depth = 1 + θ/60°. It exposes exactly what the runtime fed the network."""
    from torch import nn

    from bmi_sdk.runtime import export_model

    class PassThrough(nn.Module):
        def forward(self, x):
            return x[:, :3] * 1.0, 1.0 + x[:, 3:4]

    return export_model(PassThrough(), tmp_path_factory.mktemp("passthrough") / "pass.onnx", preset="test-pass")


@pytest.fixture(scope="session")
def bmi():
    """``bmi(*args, check=True, cwd=None)``: run ``bmi ARGS`` (``python -m bmi_sdk.cli``, arguments passed through
    ``str``) in a fresh interpreter and return the ``CompletedProcess`` with its text output. With ``check`` a
    non-zero exit fails the test and shows the end of stderr; ``check=False`` is for tests of refusals."""

    def run(*args, check: bool = True, cwd=None) -> subprocess.CompletedProcess:
        done = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", *map(str, args)], capture_output=True, text=True,
                              cwd=cwd, timeout=SUBPROCESS_PATIENCE_S)
        if check:
            command = " ".join(map(str, args))
            assert done.returncode == 0, f"bmi {command} exited {done.returncode}: {done.stderr[-3000:]}"
        return done

    return run


@pytest.fixture(scope="session")
def exit_code():
    """``bmi ARGV`` run in this process, as its exit status: ``main``'s return, or argparse's ``SystemExit`` code
    (2) for a value an option's type refuses."""
    from bmi_sdk.cli import main

    def run(argv: list[str]) -> int:
        try:
            return main(argv)
        except SystemExit as exc:
            return int(exc.code)

    return run
