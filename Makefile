# Two commands do all set-up on a fresh machine:
#   make demo   install into .venv if needed, then fly the demo on the simulated lab
#   make test   install into .venv if needed, then run the test suite
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test install bench lint clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/flightkit demo

# Two workers (pytest-xdist): the wall-paced simulator tests run one after another in one of them
# (tests/conftest.py, PACED_MODULES), everything else shares out over both.
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadgroup --durations=25

bench: $(STAMP)
	@for b in bench/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

lint: $(STAMP)
	$(VENV)/bin/ruff check flightkit trajectories capture estimation tests bench
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
