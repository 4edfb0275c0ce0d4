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
    ("import bmi_sdk.nn.metrics", ("torch",)),
    ("import bmi_sdk.nn.data", ("torch",)),
    ("import bmi_sdk.runtime", ("torch", "jax", "bmi_sdk.nn", "bmi_sdk.bench", "bmi_sdk.cli")),
    ("import calibration.io", ("jax", "jaxopt", "calibration.fit")),  # bmi infer --calibration (issue 14)
    ("import bmi_sdk.scenes", ("h5py", "torch")),  # bmi simulate's procedural scenes
])
def test_import_loads_only_what_it_needs(statement, absent):
    assert _loaded_after(statement, absent) == dict.fromkeys(absent, False)


def test_nn_public_names_resolve_lazily():
    # a submodule is reachable as an attribute too, imported on first use
    assert _loaded_after("import bmi_sdk.nn as nn; nn.metrics", ("bmi_sdk.nn.metrics",)) == {"bmi_sdk.nn.metrics": True}
    import bmi_sdk.nn as nn

    for name in nn.__all__:
        assert getattr(nn, name) is getattr(sys.modules[f"bmi_sdk.nn.{nn._HOME[name]}"], name)
    assert set(nn.__all__) <= set(dir(nn))
    assert nn.train is sys.modules["bmi_sdk.nn.train"]  # the submodule; the loop is nn.train.train
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        nn.nope  # noqa: B018
