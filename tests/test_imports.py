"""Importing a package changes nothing and loads only what it needs (issue 15, section 4).

Each check runs in a fresh interpreter: in the test process everything is
already imported.
"""

import json
import subprocess
import sys

import pytest


def _loaded_after(statement: str, modules: tuple[str, ...]) -> dict:
    script = (f"import json, sys\n{statement}\n"
              f"print(json.dumps({{m: m in sys.modules for m in {list(modules)!r}}}))")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.splitlines()[-1])


@pytest.mark.parametrize("statement, absent", [
    ("import bmi_sdk.metrics", ("torch", "bmi_sdk.nn")),
    # bmi demo's error against the ground truth uses the metrics without the training package
    ("import numpy as np; from bmi_sdk.cli.demo import errors_against_truth; "
     "errors_against_truth(np.ones((2, 2, 3)), np.ones((2, 2)), np.ones((2, 2), bool), "
     "type('Scene', (), {'rgb': np.ones((2, 2, 3)), 'range_m': np.ones((2, 2))}))", ("torch", "bmi_sdk.nn")),
    ("import bmi_sdk.nn.data", ("torch",)),
    ("import bmi_sdk.runtime", ("torch", "jax", "bmi_sdk.nn", "bmi_sdk.bench", "bmi_sdk.cli")),
    # a host talking to a real camera needs neither the simulator nor the optics behind its scenes
    ("import devices", ("firmware_sim", "bmi_sdk.optics", "bmi_sdk.render", "scipy", "cv2")),
    ("import firmware_sim", ("bmi_sdk.optics", "bmi_sdk.render", "scipy", "cv2")),
    ("import bmi_sdk.protocol.wire", ("bmi_sdk.geometry", "devices", "firmware_sim", "scipy", "cv2")),
    ("import calibration.io", ("jax", "jaxopt", "calibration.fit")),  # bmi infer --calibration (issue 14)
    ("import bmi_sdk.scenes", ("h5py", "torch")),  # bmi simulate's procedural scenes
])
def test_import_loads_only_what_it_needs(statement, absent):
    assert _loaded_after(statement, absent) == dict.fromkeys(absent, False)


def test_nn_public_names_resolve_lazily():
    # a submodule is reachable as an attribute too, imported on first use
    assert _loaded_after("import bmi_sdk.nn as nn; nn.data", ("bmi_sdk.nn.data",)) == {"bmi_sdk.nn.data": True}
    import bmi_sdk.nn as nn

    for name in nn.__all__:
        assert getattr(nn, name) is getattr(sys.modules[f"bmi_sdk.nn.{nn._HOME[name]}"], name)
    assert set(nn.__all__) <= set(dir(nn))
    assert nn.train is sys.modules["bmi_sdk.nn.train"]  # the submodule; the loop is nn.train.train
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        nn.nope  # noqa: B018
