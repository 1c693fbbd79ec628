# rotortwin: two commands on a fresh machine (see README)
#   make setup  the venv, then the generated numba code compiled into ~/.cache/rotortwin/numba (fleet warm)
#   make demo   set up, then run the main job on the shipped flight in bags/
#   make test   set up, then run the test suite (what .ci/run calls)
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
DEMO_FLIGHT ?= bags/sim_quadx_weak_motor3.ulg
DEMO_PARAMS ?= params/px4_sih_quadx.yaml
OUT ?= out/demo

.PHONY: setup demo test bench clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[ros,dev]'
	$(BIN)/rotortwin fleet warm || echo "rotortwin: compiling ahead failed; the first run compiles instead"
	touch $@

demo: setup
	bash launch_scripts/demo.sh $(DEMO_FLIGHT) $(DEMO_PARAMS) $(OUT)

test: setup
	$(BIN)/python -m pytest -q -m "not slow" -p no:cacheprovider

# every benchmark, each with its defaults (bench/README.md); ROTORTWIN_BENCH_SMOKE=1 for a quick smoke run
bench: setup
	for b in bench/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) out
