# Two set-up commands on a fresh machine: `make sim` and `make test`.
# Each creates .venv (if missing) and installs what it needs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test test-stress sim bench fuzz venv clean regen-messages

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,sim]'
	touch $(STAMP)

venv: $(STAMP)

# Two pytest-xdist workers: most of the suite's time is spent waiting on real processes (services
# starting, timeouts), so two halve the wall time on two cores. PYTEST_WORKERS=0 runs it serially.
PYTEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -n $(PYTEST_WORKERS) $(PYTEST_ARGS)

# The suite while busy processes keep every core loaded, as on a shared CI machine.
test-stress: $(STAMP)
	$(PY) bench/cpu_hog.py -- $(PY) -m pytest -n $(PYTEST_WORKERS) $(PYTEST_ARGS)

sim: $(STAMP)
	$(VENV)/bin/u2sa sim --vehicle examples/ground_vehicle/vehicle.toml --out sim-out

bench: $(STAMP)
	$(PY) bench/transport.py

# Long fuzzing of every parser (bench/fuzz.py): atheris (coverage-guided) where it installs,
# else the seeded mutator the tests use briefly. FUZZ_SECONDS per target.
FUZZ_SECONDS ?= 60
fuzz: $(STAMP)
	$(PY) -m pip install --quiet atheris || echo "atheris does not install here: the seeded mutator runs instead"
	$(PY) bench/fuzz.py --seconds $(FUZZ_SECONDS)

regen-messages: $(STAMP)
	$(PY) -m u2sa_hw.message_codegen

clean:
	rm -rf $(VENV) build *.egg-info sim-out
