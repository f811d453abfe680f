# Set-up and entry points. Only Python 3.11, git and make are assumed on the machine.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= demo_out

# Third-party robot hand models used by tests and examples: installed from their wheels,
# never committed. --no-deps because only their data files are needed.
ROBOT_MODEL_WHEELS := "ghand==0.1.*" "gymnasium-robotics==1.4.*"

.PHONY: setup demo test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	$(BIN)/python -m pip install --quiet --no-deps $(ROBOT_MODEL_WHEELS)
	touch $(STAMP)

demo: setup
	$(BIN)/handretarget demo --out $(DEMO_OUT)

test: setup
	$(BIN)/python -m pytest

bench: setup
	$(BIN)/handretarget bench kinematics
	$(BIN)/handretarget bench pairing
	$(BIN)/handretarget bench transfer
	$(BIN)/handretarget bench

clean:
	rm -rf $(VENV) $(DEMO_OUT)
