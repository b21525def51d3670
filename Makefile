# crossmodal: `make run` starts the simulated workcell, `make test` runs the tests.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEPLOYMENT ?= deploy/sim.toml
# The network the policy service serves (runs/policy/policy.pt), from the world's scripted teacher;
# nothing is downloaded. `make run` does not wait for it: when it is missing the dashboard trains it
# as a job (progress in its Learn folder, about 10 min on 2 cores) while the cell runs on the naive
# fallback, which replays the job's training demonstrations (runs/policy/demos/, written first); the
# policy service switches to the network once it is written. `make policy` trains it in the terminal.
POLICY_PRESET ?= no_tactile
# its optimizer steps: the panel's first_steps, fewer than the preset's (docs/panel.md, first run)
POLICY_STEPS ?= 5000
POLICY := runs/policy/policy.pt
# The keypoint network recon runs ships in models/detector/ (ONNX graphs + their JSON): `make detector`
# regenerates it: labels rendered from the simulated rig, then training of the first stage (whole
# windows; about 20 min on 2 idle cores), of the second (one hand per crop; minutes) and of the
# object stage, then a second learning-rate cycle of the first and second stages from those weights
# (about 15 min), then their int8 copies recon runs (calibrated on the labelled set,
# seconds); the labelled sets, the torch weights and the loss plots stay in runs/detector/.
# The glove's cell map (which readout crossing is which sensor's cell, and where each cell lies on
# the hand) ships in models/skin/glove_cellmap.json: the layout the glove service and the tactile
# projection read; `make cellmap` writes it again from the skin tools' glove design (skin/examples.py).
DETECTOR_ITERS ?= 6500
DETECTOR_MINUTES ?= 90
DETECTOR_HAND_ITERS ?= 5000
DETECTOR_HAND_MINUTES ?= 20
DETECTOR_OBJECT_ITERS ?= 2800
DETECTOR_OBJECT_MINUTES ?= 20
DETECTOR_TUNE_ITERS ?= 1500
DETECTOR_HAND_TUNE_ITERS ?= 2000

.PHONY: run test test-fast bench soak lint clean help policy detector cellmap

help:
	@echo "make run    - the whole workcell on the simulated default; dashboard at http://127.0.0.1:8080"
	@echo "make test   - the test suite (unit, contract, integration, HDL, browser)"
	@echo "make policy - train the network the policy service serves (runs/policy/policy.pt)"
	@echo "make detector - regenerate recon's keypoint network (models/detector/)"
	@echo "make cellmap - regenerate the glove's cell map (models/skin/glove_cellmap.json)"
	@echo "make bench  - benchmarks, results in .bench/*.json"
	@echo "make soak   - chaos soak: kill -9 a random service every minute for an hour (.bench/soak.json)"
	@echo "make lint   - ruff"

$(STAMP): pyproject.toml tests/lerobot_check/requirements.txt
	test -d $(VENV) || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# torch first and pinned: the CPU wheel lies on disk; any other spec downloads gigabytes.
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev,baselines]'
	# LeRobot's dataset class for the export tests, beside the venv (it pins an older torch; docs/lerobot.md)
	$(BIN)/pip install -q --target .cache/lerobot-site --no-deps --upgrade -r tests/lerobot_check/requirements.txt
	# compile the policy's horizon loop once (numba caches it; about 20 s)
	$(BIN)/python -c "from services.policy.compiled import warm; warm()"
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/xm up $(DEPLOYMENT) --open

policy: $(POLICY)

# trained again when the checkpoint's configs change (a checkpoint of other configs does not load)
$(POLICY): $(STAMP) services/policy/config.py
	$(BIN)/xm train --teacher 0 --preset $(POLICY_PRESET) --steps $(POLICY_STEPS) --out $(dir $(POLICY))

detector: $(STAMP)
	$(BIN)/xm detector label --out runs/detector/labels
	$(BIN)/xm detector train --labels runs/detector/labels/train --out runs/detector \
		--iters $(DETECTOR_ITERS) --minutes $(DETECTOR_MINUTES)
	mkdir -p models/detector
	$(BIN)/xm detector train-hands --labels runs/detector/labels/train --out runs/detector \
		--iters $(DETECTOR_HAND_ITERS) --minutes $(DETECTOR_HAND_MINUTES) --threads 2
	$(BIN)/xm detector train-objects --labels runs/detector/labels/train --out runs/detector --init runs/detector \
		--iters $(DETECTOR_OBJECT_ITERS) --minutes $(DETECTOR_OBJECT_MINUTES)
	$(BIN)/xm detector train --labels runs/detector/labels/train --out runs/detector --init runs/detector \
		--iters $(DETECTOR_TUNE_ITERS) --minutes 30 --lr 5e-4
	$(BIN)/xm detector train-hands --labels runs/detector/labels/train --out runs/detector --init runs/detector \
		--iters $(DETECTOR_HAND_TUNE_ITERS) --minutes 15 --lr 5e-4 --threads 2
	$(BIN)/xm detector quantize --weights runs/detector --labels runs/detector/labels/train
	cp runs/detector/model.onnx runs/detector/meta.json runs/detector/hands.onnx runs/detector/hands.json \
		runs/detector/objects.onnx runs/detector/objects.json runs/detector/model.int8.onnx \
		runs/detector/hands.int8.onnx runs/detector/objects.int8.onnx models/detector/
	$(BIN)/xm detector eval --weights models/detector --labels runs/detector/labels/eval

cellmap: $(STAMP)
	$(BIN)/xm skin glove --cellmap-only --out models/skin

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -ra

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -ra -m "not slow and not browser and not hdl"

bench: $(STAMP)
	mkdir -p .bench
	for b in bench/[!_]*.py; do [ $$b = bench/soak.py ] && continue; echo "== $$b"; PYTHONPATH=. $(BIN)/python $$b || exit 1; done

SOAK_MINUTES ?= 60
soak: $(STAMP)
	mkdir -p .bench
	PYTHONPATH=. $(BIN)/python bench/soak.py --minutes $(SOAK_MINUTES)

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache sim_build
