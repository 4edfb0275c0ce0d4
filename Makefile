# Two entry points (README): `make demo` and `make test`. Both create the virtual
# environment on first use and install the project with every extra (`.[test]`
# pulls `[all]`: train, calibrate, scaleout, plot) and the pinned constraints.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-all lint install clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip -c constraints.txt
	$(PY) -m pip install -q -c constraints.txt -e '.[test]'
	$(PY) -c "import torch, sys; v = torch.__version__; sys.exit(0 if v.startswith('2.13.0') and '+cpu' in v else 'resolver pulled torch ' + v)"
	touch $(STAMP)

install: $(STAMP)

# A 1536×1024 window of the embedded scene by default; `make demo DEMO_ARGS=--full-frame` for the whole sensor
# (bmi demo --help).
demo: $(STAMP)
	$(VENV)/bin/bmi demo $(DEMO_ARGS)

# The static checks, fastest first: lint ([tool.ruff]), the types of the public API packages ([tool.mypy]) and the
# import contracts ([tool.importlinter], docs/architecture.md); each configured in pyproject.toml.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports --no-cache

# `make test` (CI's command) leaves out the tests marked slow: exhaustive references and repeats of what a faster
# test covers (pyproject.toml, [tool.pytest.ini_options]); `make test-all` runs them too.
test: lint
	$(PY) -m pytest -m "not slow"

test-all: lint
	$(PY) -m pytest

clean:
	rm -rf $(VENV) build *.egg-info
