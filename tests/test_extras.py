"""Install weight (issue 14): ``pip install bmi-sdk`` decodes; training, the calibration fit, Dask and plots are extras.

A decode-only install is stood in for by a fresh interpreter whose import
system refuses every module an extra provides: a ``sys.meta_path`` finder
raises ``ModuleNotFoundError``, as a missing package does. No second virtual
environment is needed, and the test process itself keeps everything.
"""

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
EXTRA_MODULES = ("torch", "kornia", "onnx", "h5py", "jax", "jaxlib", "jaxopt", "dask", "distributed", "matplotlib")
"""Every module the extras provide: none of them is installed in a decode-only environment."""

BOOTSTRAP = """
import sys

BLOCKED = set(sys.argv.pop(1).split(","))


class NotInstalled:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, NotInstalled())
"""


def _python_without(blocked, code: str, *args) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter where the ``blocked`` modules cannot be imported."""
    return subprocess.run([sys.executable, "-c", BOOTSTRAP + code, ",".join(blocked), *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT)


def _bmi_without(blocked, *args) -> subprocess.CompletedProcess:
    """``bmi ARGS`` in a fresh interpreter where the ``blocked`` modules cannot be imported."""
    return _python_without(blocked, "from bmi_sdk.cli import main\nsys.exit(main(sys.argv[1:]))", *args)


@pytest.fixture(scope="module")
def frame_and_calibration(tmp_path_factory):
    """A frame from the simulated camera (acquired decode-only too) and a calibration file of that camera
    (decenter 8 µm).

    The file is written from a stated fit result, without running the fit: this test is about who can read
    the file, and tests/test_calibration.py tests the fit.
    """
    from bmi_sdk.optics.perturb import VECTOR_NAMES, Perturbation
    from calibration import CapturePlan, FitResult, PointSource, Target, simulate_captures, write_calibration

    tmp = tmp_path_factory.mktemp("decode_only")
    run = _bmi_without(EXTRA_MODULES, "acquire", "--device", "sim://decode-only", "--count", 1, "--scene", "chart",
                       "--roi", "4200,2200,96,96", "--out", tmp / "frames")
    assert run.returncode == 0, run.stderr[-3000:]
    (frame,) = (tmp / "frames").glob("*.dng")
    truth = Perturbation(decenter_um=(8.0, 0.0))
    captures = simulate_captures(Target((PointSource(0.0, 0.0, 4.0),)), CapturePlan(kernel_px=21, roi_margin_px=10),
                                 truth, seed=1)
    n = len(VECTOR_NAMES)
    result = FitResult(estimate=truth, vector=truth.to_vector(), sigma=np.full(n, 0.1), free=np.ones(n, bool),
                       correlation=np.eye(n), chi2_reduced=1.0, n_pixels=0, n_parameters=n, outer_iterations=0,
                       inner_iterations=[], per_capture=[], held_out=[], degeneracies=[], seconds={})
    calib = write_calibration(tmp / "calib.json", result, captures, tensor_fields_deg=(0.0,), tensor_depths_m=(4.0,),
                              report=False)
    return frame, calib


@pytest.mark.parametrize("decoder", ["classical", "cnn"])
def test_infer_with_a_calibration_file_needs_no_extra(frame_and_calibration, tmp_path, decoder):
    """The decode path, calibration file included, runs with none of the extras' modules importable."""
    frame, calib = frame_and_calibration
    knobs = ("--candidates", 12) if decoder == "classical" else ()  # a classical option; other decoders refuse it
    run = _bmi_without(EXTRA_MODULES, "infer", frame, "--out", tmp_path / "o", "--decoder", decoder,
                       "--calibration", calib.path, *knobs, "--quiet")
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    if decoder == "cnn":  # the file is validated; no model was trained for it, so the nominal one runs
        assert report["calibration_file"]["id"] == calib.id
    else:  # the calibrated camera built the kernels
        assert report["calibration_id"] == calib.id
        assert report["camera"]["perturbation"]["decenter_um"] == [8.0, 0.0]


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _name(requirement: str) -> str:
    return re.sub(r"[-_.]+", "-", re.split(r"[<>=!~\[ ;]", requirement)[0]).lower()


def test_core_requirements_hold_neither_torch_nor_jax_and_pins_live_in_constraints():
    project = _pyproject()
    core = {_name(r) for r in project["dependencies"]}
    assert core & {"torch", "kornia", "jax", "jaxlib", "jaxopt", "onnx", "h5py", "matplotlib", "dask"} == set()
    extras = project["optional-dependencies"]
    assert {"torch", "kornia"} <= {_name(r) for r in extras["train"]}
    assert {"jax", "jaxlib", "jaxopt"} <= {_name(r) for r in extras["calibrate"]}
    every = project["dependencies"] + [r for reqs in extras.values() for r in reqs]
    assert [r for r in every if "==" in r] == []  # exact pins belong in constraints.txt
    pins = (ROOT / "constraints.txt").read_text().split()
    assert {"torch==2.13.0", "kornia==0.9.0", "jax==0.10.2", "jaxlib==0.10.2"} <= set(pins)


def test_the_test_extra_installs_every_other_extra():
    """``make test`` and ``make demo`` install ``.[test]``: it must reach every extra (through ``[all]``)."""
    extras = _pyproject()["optional-dependencies"]

    def reached(extra: str, seen: set) -> set:
        seen.add(extra)
        for r in extras[extra]:
            if _name(r) == "bmi-sdk":
                for e in re.search(r"\[(.*)\]", r).group(1).split(","):
                    if e.strip() not in seen:
                        reached(e.strip(), seen)
        return seen

    assert reached("test", set()) == set(extras) >= {"train", "calibrate", "scaleout", "plot"}
    assert "'.[test]'" in (ROOT / "Makefile").read_text()


def test_every_extra_module_is_named_by_the_extra_that_installs_it():
    """``EXTRA_OF_MODULE`` (what the one-line error names) agrees with pyproject.toml."""
    import importlib.metadata

    from bmi_sdk.extras import EXTRA_OF_MODULE

    extras = _pyproject()["optional-dependencies"]
    dists = importlib.metadata.packages_distributions()
    assert set(EXTRA_OF_MODULE) == set(EXTRA_MODULES)
    for module, extra in EXTRA_OF_MODULE.items():
        # a requirement's own extras count as the distributions they pull (dask[distributed] → distributed)
        names = {_name(r) for r in extras[extra]}
        names |= {_name(e) for r in extras[extra] for group in re.findall(r"\[(.*?)\]", r) for e in group.split(",")}
        assert {_name(d) for d in dists[module]} & names, (module, extra)


@pytest.mark.parametrize("blocked, args, extra", [
    ("torch", ["train", "--out", "{tmp}/run"], "train"),
    ("jax", ["calibrate", "--simulate", "decenter_um=8,0", "--out", "{tmp}/c.json"], "calibrate"),
    ("matplotlib", ["crlb", "--json", "--plot", "{tmp}/crlb.png"], "plot"),  # before the minutes of computing
])
def test_a_missing_extra_is_one_line_naming_it(tmp_path, blocked, args, extra):
    run = _bmi_without([blocked], *[a.format(tmp=tmp_path) for a in args])
    assert run.returncode == 1
    assert run.stderr.strip() == (f"bmi {args[0]}: error: this command needs the [{extra}] extra: "
                                  f"pip install 'bmi-sdk[{extra}]' (no module named '{blocked}')")


def test_scheduler_without_dask_is_one_line_naming_the_scaleout_extra(frame_and_calibration, tmp_path):
    frame, _ = frame_and_calibration
    run = _bmi_without(["dask", "distributed"], "infer", frame, "--out", tmp_path / "o", "--scheduler", "local:1")
    assert run.returncode == 1
    assert run.stderr.strip() == ("bmi infer: error: --scheduler needs the [scaleout] extra: "
                                  "pip install 'bmi-sdk[scaleout]' (no module named 'dask')")


def test_calibration_files_read_without_jax_and_the_fit_names_its_extra(frame_and_calibration):
    _, calib = frame_and_calibration
    run = _python_without(["jax", "jaxlib", "jaxopt"], "import calibration\n"
                          "print(calibration.load_calibration(sys.argv[1]).id)\n"
                          "calibration.fit_calibration", calib.path)
    assert run.stdout.strip() == calib.id
    assert run.stderr.strip().splitlines()[-1] == (
        "bmi_sdk.extras.MissingExtraError: calibration.fit_calibration needs the [calibrate] extra: "
        "pip install 'bmi-sdk[calibrate]' (no module named 'jax')")


def test_a_missing_module_no_extra_provides_is_not_blamed_on_an_extra():
    """A broken install or a bug keeps its own ModuleNotFoundError (and, in ``bmi``, its traceback)."""
    from bmi_sdk.extras import MissingExtraError, needs_extra

    with pytest.raises(ModuleNotFoundError) as info:
        with needs_extra("this"):
            import bmi_sdk_no_such_module  # noqa: F401
    assert not isinstance(info.value, MissingExtraError)


def test_a_missing_extra_error_survives_pickling():
    """It may be raised in a task on a Dask worker and re-raised in the client."""
    import pickle

    from bmi_sdk.extras import MissingExtraError

    error = pickle.loads(pickle.dumps(MissingExtraError("--scheduler", "scaleout", "dask")))
    assert str(error) == ("--scheduler needs the [scaleout] extra: pip install 'bmi-sdk[scaleout]' "
                          "(no module named 'dask')")
    assert (error.extra, error.name) == ("scaleout", "dask")
