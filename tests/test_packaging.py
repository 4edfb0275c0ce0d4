"""The wheel holds every file the package reads at run time, and works installed (issue 15, section 6).

The wheel is built from a copy of the files git would commit (tracked plus
untracked-but-not-ignored), as a fresh clone has them: a build in the working
tree could pick up a stale ``build/`` folder. It is installed into a new,
empty virtual environment whose only other entry is a ``.pth`` line naming
this environment's site-packages for the dependencies: a path line does not
run the ``.pth`` files there, so the editable install of the checkout stays
out, and the test checks that ``bmi_sdk`` is imported from the wheel.
"""

import email
import os
import re
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("bmi_sdk", "calibration", "devices", "firmware_sim")


def _committable_files() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs a git checkout to know which files a clone has")
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout
    return [f for f in out.split("\0") if f and (ROOT / f).is_file()]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    files = _committable_files()
    for f in files:
        (tmp / "src" / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / f, tmp / "src" / f)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                    "-w", str(tmp / "dist"), str(tmp / "src")], check=True, capture_output=True, text=True)
    (whl,) = (tmp / "dist").glob("bmi_sdk-*.whl")
    return tmp, files, whl


def test_wheel_holds_every_package_file(wheel):
    _, files, whl = wheel
    names = set(zipfile.ZipFile(whl).namelist())
    package_files = {f for f in files if f.split("/", 1)[0] in PACKAGES}
    data = {f for f in package_files if not f.endswith(".py")}
    assert "bmi_sdk/data/spectral/rgb_response.json" in data and "bmi_sdk/models/default.onnx" in data
    assert sorted(package_files - names) == []


def test_installed_wheel_runs_bmi_lens(wheel):
    tmp, _, whl = wheel
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    deps = site.getsitepackages() + [sysconfig.get_paths()["purelib"]]
    (Path(purelib) / "_bmi_test_deps.pth").write_text("\n".join(dict.fromkeys(deps)) + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps", "--no-index",
                    str(whl)], check=True, capture_output=True, text=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    run = tmp / "elsewhere"
    run.mkdir()
    where = subprocess.run([str(python), "-I", "-c", "import bmi_sdk, bmi_sdk.optics.spectral as s; "
                            "s.integrated(); print(bmi_sdk.__file__)"],  # integrated() reads data/spectral
                           cwd=run, env=env, capture_output=True, text=True)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).is_relative_to(venv)
    lens = subprocess.run([str(venv / "bin" / "bmi"), "lens"], cwd=run, env=env, capture_output=True, text=True)
    assert lens.returncode == 0, lens.stderr
    assert "lens bmi_monocentric" in lens.stdout and "f_number                          1.78858" in lens.stdout


def test_wheel_metadata_asks_only_what_decoding_needs(wheel):
    """``pip install bmi-sdk`` (no extra) installs neither torch nor jax: the wheel's unconditional
    requirements hold neither, and each extra is declared."""
    _, _, whl = wheel
    with zipfile.ZipFile(whl) as z:
        (meta,) = [n for n in z.namelist() if n.endswith(".dist-info/METADATA")]
        headers = email.message_from_bytes(z.read(meta))
    unconditional = {re.split(r"[<>=!~\[ ;]", r)[0].lower() for r in headers.get_all("Requires-Dist")
                     if "extra ==" not in r}
    assert "numpy" in unconditional and "onnxruntime" in unconditional
    assert unconditional & {"torch", "kornia", "jax", "jaxlib", "jaxopt"} == set()
    assert {"train", "calibrate", "scaleout", "plot", "all", "test"} <= set(headers.get_all("Provides-Extra"))


NOT_IMPORTED = {"jaxlib": "jax's compiled backend: jax imports it; declared beside jax in [calibrate], and "
                          "constraints.txt pins both to one version",
                "kornia": "the users' chosen library for image operations on torch tensors; no torch-side image "
                          "operation exists yet (docs/architecture.md, Packaging)"}
"""Declared dependencies the code does not import itself, each with the reason it is declared."""

RUNTIME_EXTRAS = ("train", "calibrate", "scaleout", "plot")
"""The extras the code uses (``bmi_sdk.extras``); ``all`` and ``test`` only gather them and the test tools."""


def test_every_declared_dependency_is_imported():
    """A dependency nothing imports costs every install and misleads readers: each exception says why.
    Checked for the core requirements and for each extra the code uses."""
    import importlib.metadata
    import tomllib

    import grimp

    def norm(name):
        return re.sub(r"[-_.]+", "-", name).lower()

    graph = grimp.build_graph(*PACKAGES, include_external_packages=True, cache_dir=None)
    imported = {m.split(".")[0] for m in graph.modules if not m.startswith(PACKAGES)}
    module_dists = importlib.metadata.packages_distributions()
    used = {norm(d) for m in imported for d in module_dists.get(m, ())}
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = project["dependencies"] + [r for e in RUNTIME_EXTRAS for r in project["optional-dependencies"][e]]
    names = {norm(re.split(r"[<>=!~\[ ;]", d)[0]) for d in declared}
    assert sorted(names - used - set(NOT_IMPORTED)) == []
