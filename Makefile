# Two set-up commands on a fresh machine: `make sim` and `make test`.
# Each creates .venv (if missing) and installs what it needs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test test-stress test-pythons sim bench fuzz venv clean regen-messages

$(STAMP): pyproject.toml setup.py
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

# The quick tests under other interpreters (docs/python-versions.md): each one found, on PATH or in
# pyenv's versions, gets its own .venv-X.Y; one not found is named and skipped, not a failure.
PYTHONS ?= python3.12 python3.13
PYENV_VERSIONS ?= $(or $(PYENV_ROOT),$(HOME)/.pyenv)/versions
# In-process unit tests plus a few short service runs: messages, config, bus auth and transport,
# NMEA/GPS, ODrive/VESC protocols and drivers, pre-arm, the launcher, the registry's lean imports.
QUICK_TESTS ?= tests/test_messages.py tests/test_fuzz_lcm.py tests/test_config.py tests/test_config_keys.py \
	tests/test_profile_keys.py tests/test_param_ranges.py tests/test_bus_auth.py tests/test_bus_filter.py \
	tests/test_transport.py tests/test_udp_ports.py tests/test_driver_gps.py tests/test_gps_epochs.py \
	tests/test_gps_merge.py tests/test_gps_streams.py tests/test_gps_fuzz.py tests/test_protocol_odrive.py \
	tests/test_protocol_vesc.py tests/test_driver_odrive.py tests/test_driver_vesc.py tests/test_stall_trip.py \
	tests/test_fuzz_can.py tests/test_port_can.py tests/test_prearm.py tests/test_imu_rest.py \
	tests/test_launcher.py tests/test_launcher_cgroup.py tests/test_realtime.py tests/test_realtime_launcher.py \
	tests/test_registry.py tests/test_safety_chain.py tests/test_control.py tests/test_estimator_ekf.py \
	tests/test_mission.py tests/test_log_chunk_parse.py
test-pythons:
	@failed=""; \
	for want in $(PYTHONS); do \
	  exe=""; \
	  if $$want -c "" >/dev/null 2>&1; then exe=$$want; \
	  else exe=$$(ls -d $(PYENV_VERSIONS)/$${want#python}.*/bin/$$want 2>/dev/null | sort -V | tail -n 1); fi; \
	  if [ -z "$$exe" ]; then echo "$$want: not installed; skipped"; continue; fi; \
	  ver=$$($$exe -c 'import sys; print("%d.%d" % sys.version_info[:2])'); venv=.venv-$$ver; \
	  echo "== $$want: $$($$exe -c 'import sys; print(sys.executable, sys.version.split()[0])') in $$venv"; \
	  if [ ! $$venv/.installed -nt pyproject.toml ]; then \
	    { test -x $$venv/bin/python || $$exe -m venv $$venv; } && \
	    $$venv/bin/python -m pip install --quiet --upgrade pip && \
	    $$venv/bin/python -m pip install --quiet -e '.[test]' && touch $$venv/.installed \
	    || { echo "$$want: the install into $$venv failed (above)"; failed="$$failed $$want"; continue; }; \
	  fi; \
	  start=$$(date +%s); ok=yes; \
	  $$venv/bin/python -m pytest -n $(PYTEST_WORKERS) $(PYTEST_ARGS) $(QUICK_TESTS) || ok=no; \
	  $$venv/bin/python bench/pythons.py || ok=no; \
	  echo "== $$want: $$([ $$ok = yes ] && echo passed || echo FAILED) in $$(( $$(date +%s) - start )) s"; \
	  [ $$ok = yes ] || failed="$$failed $$want"; \
	done; \
	if [ -n "$$failed" ]; then echo "test-pythons failed under:$$failed"; exit 1; fi

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
	rm -rf $(VENV) .venv-3.* build *.egg-info sim-out
