# Set-up and entry points. Only Python 3.11, git and make are assumed on the machine.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Blender's Python module (bpy pins numpy < 2) lives in its own venv, for the add-in's tests
BLENDER_VENV := .venv-blender
BLENDER_STAMP := $(BLENDER_VENV)/.installed
BPY := "bpy==5.0.1"
DEMO_OUT ?= demo_out

# Third-party robot hand models used by tests and examples: installed from their wheels,
# never committed. --no-deps because only their data files are needed.
ROBOT_MODEL_WHEELS := "ghand==0.1.*" "gymnasium-robotics==1.4.*"

.PHONY: setup demo test bench extension clean

setup: $(STAMP) $(BLENDER_STAMP)

$(STAMP): pyproject.toml Makefile
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	$(BIN)/python -m pip install --quiet --no-deps $(ROBOT_MODEL_WHEELS)
	touch $(STAMP)

$(BLENDER_STAMP): Makefile
	$(PY) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(BLENDER_VENV)/bin/python -m pip install --quiet $(BPY) "pytest>=8,<10"
	touch $(BLENDER_STAMP)

demo: setup
	$(BIN)/handretarget demo --out $(DEMO_OUT)

# the service tests beside the core tests and then the Blender add-in's, one lane per core
# (tests/run_lanes.sh; either lane failing or collecting nothing fails the target)
test: setup
	bash tests/run_lanes.sh $(BIN) $(BLENDER_VENV)/bin

extension: setup
	$(BLENDER_VENV)/bin/python dcc_client/build_extension.py --out dist

bench: setup
	$(BIN)/handretarget bench kinematics
	$(BIN)/handretarget bench pairing
	$(BIN)/handretarget bench transfer
	$(BIN)/handretarget bench

clean:
	rm -rf $(VENV) $(BLENDER_VENV) $(DEMO_OUT) dist
