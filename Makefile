# ibr_pipeline — the two commands a newcomer needs:  `make demo`  and  `make test`.
PYTHON ?= python3
VENV   ?= .venv
OUT    ?= out
JOBS   ?= 2
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install demo demo-full view test test-slow bench clean-demo help

help:
	@echo "make demo       install, then run the pipeline on sample_data/ (results in $(OUT)/demo)"
	@echo "make view       serve the browser viewer of $(OUT)/demo on http://127.0.0.1:8000/ (after make demo)"
	@echo "make test       install, then run the test suite (fast tests)"
	@echo "make test-slow  install, then run only the slow tests"
	@echo "make install    system libraries (apt-get, when missing) + virtualenv $(VENV)"
	@echo "make demo-full  the same on a full-size (640x480, 120 views) synthetic scene"
	@echo "make bench      install, then ibr bench pipeline mirror_room --stability (charts in $(OUT)/bench)"

install: $(STAMP)

$(STAMP): pyproject.toml requirements.lock scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), f"Python 3.11 needed, {sys.version.split()[0]} found (set PYTHON=...)"'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.lock
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e . 2>/dev/null || \
		$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

# the demo trains DSRNet for its fixed number of steps (no time budget) on one torch thread (the
# weights depend on the thread count, which the automatic choice takes from the machine's load),
# so its figures are the same on a quiet and on a loaded machine
DEMO_SET := --set supersample.time_budget_s=0 --set supersample.train.threads=1

demo: install
	$(BIN)/ibr run $(OUT)/demo --input sample_data/mirror_room --jobs $(JOBS) $(DEMO_SET)
	$(BIN)/ibr status $(OUT)/demo $(DEMO_SET)
	$(BIN)/ibr report $(OUT)/demo $(if $(wildcard $(OUT)/bench/results.jsonl),--bench $(OUT)/bench)
	@echo "demo done: open $(OUT)/demo/report/index.html; walk through it in a browser: make view"

view: install
	$(BIN)/ibr view $(OUT)/demo

test: install
	$(BIN)/python -m pytest

test-slow: install
	$(BIN)/python -m pytest -m slow

# full size: a 640x480, 120-view synthetic mirror_room (generation ~1.5 min, then every stage). Its
# RGB-D sensor has the images' resolution (--depth-scale 1.0; ibr synth's default is half): Xu et
# al. build G from MVS of 6000x4000 photos, sharper than the images they refine (docs/VIEW_DEPTH.md)
FULL_SCENE := $(OUT)/scenes/mirror_room_rgbd640
demo-full: install
	test -f $(FULL_SCENE)/gt/scene.json || $(BIN)/ibr synth mirror_room $(FULL_SCENE) --depth-scale 1.0 --jobs $(JOBS)
	$(BIN)/ibr run $(OUT)/full_rgbd640 --input $(FULL_SCENE) --jobs $(JOBS)
	$(BIN)/ibr report $(OUT)/full_rgbd640

bench: install
	$(BIN)/ibr bench pipeline mirror_room --stability --out $(OUT)/bench

clean-demo:
	rm -rf $(OUT)/demo
