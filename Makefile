# Two commands do all set-up on a fresh machine:
#   make run    -> creates .venv, installs the locked dependencies, runs the rig (hil up) for 60 s
#   make test   -> same set-up, then the whole test suite (two pytest-xdist workers: the live
#                  tests one at a time on one, the pure ones on the other; tests/conftest.py)
PYTHON ?= python3
VENV   ?= .venv
ARGS   ?=

.PHONY: run test sim lint clean kernels

$(VENV)/.installed: pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --disable-pip-version-check -r requirements.lock
	$(VENV)/bin/python -m pip install -q --disable-pip-version-check --no-deps -e .
	$(VENV)/bin/python -m hil.runtime.aot || true
	touch $@

# the navigation kernels compiled ahead of time (hil.runtime.aot), again after editing them: until
# then numba's cached kernels run (the same bits, ~0.45 s more start-up per process)
kernels: $(VENV)/.installed
	$(VENV)/bin/python -m hil.runtime.aot

run: $(VENV)/.installed
	$(VENV)/bin/hil up $(ARGS)

sim: $(VENV)/.installed
	$(VENV)/bin/hil sim $(ARGS)

test: $(VENV)/.installed
	$(VENV)/bin/python -m pytest -n 2 $(ARGS)

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/hil schemas

clean:
	rm -rf $(VENV) recordings .pytest_cache
