# The two commands a new user needs:  `make demo`  and  `make test`  (both set up first).
VENV := .venv/bin
export PYTHONUNBUFFERED := 1

.PHONY: setup demo test test-slow lint bench flights eval eval-shared train train-loso proto clean
setup:
	@bash scripts/setup.sh

demo:                ## the main job on the bundled building (set-up installs the runtime only: no torch)
	@MACROLOC_EXTRAS=runtime bash scripts/setup.sh
	$(VENV)/macroloc demo

test: setup          ## the fast suite (< 10 min on 2 cores) + lint and type check
	$(VENV)/ruff check common graph perception proto sim service cli tests bench scripts
	bash scripts/typecheck.sh
	$(VENV)/python -m pytest -q

test-slow: setup     ## training, long flights, soak: the heavy checks behind the `slow` marker
	$(VENV)/python -m pytest -q -m slow

bench: setup         ## benchmarks, each figure printed beside its target
	MACROLOC_EXTRAS=dev,bench bash scripts/setup.sh
	$(VENV)/python -m bench.run_all

flights: setup      ## issue 5's flight table: 10 rendered flights (~4 GB, rendered once: ~20 min) x 3 noise seeds, truth
	$(VENV)/python -m bench.bench_flights $(FLIGHTS_ARGS)

eval: setup          ## the project's own localization evaluation on every bundled building
	for b in data/buildings/*.ifc; do $(VENV)/macroloc eval $$b --n 200 --seed 1; done

eval-shared: setup  ## the independent harness in ../shared/eval on every shared IFC (n=200, seed 1; ~1 h on 2 cores)
	for b in ../shared/data/bim/*.ifc; do for v in gravity full nogravity; do \
	  echo "$$b $$v: $$($(VENV)/python ../shared/eval/score_localize.py $$b --n 200 --seed 1 --variant $$v \
	    --cmd "$(CURDIR)/$(VENV)/macroloc" $(EVAL_ARGS) | tail -1)"; done; done

eval-matrix: setup    ## issue 38's table: every shared IFC x 3 variants x default/hard/3-5 observations x 2 seeds, n=200, in one process
	$(VENV)/python -m bench.eval_shared --matrix --seeds $(or $(SEEDS),8101,8202) --n 200 --out out/eval_shared

train: setup         ## reproduce the shipped detector weights (needs torch: the train extra; ~115 min on 2 cores)
	MACROLOC_EXTRAS=dev,train bash scripts/setup.sh
	$(VENV)/python -m macroloc.perception.train --out out/detector/base --report out/detector/base
	$(VENV)/python -m macroloc.perception.train --init out/detector/base/checkpoint.pt --indoor-fraction 0.35 \
	  --lr 5e-4 --steps 2000 --out out/detector/stage2 --report out/detector/stage2
	$(VENV)/python -m macroloc.perception.train --init out/detector/stage2/checkpoint.pt --sim out/sim_yolo \
	  --sim-fraction 0.25 --indoor-fraction 0.35 --lr 5e-4 --steps 1500

LOSO := python -m macroloc.perception.train --arch shufflenet --freeze first_conv stage2 --camera 0.3 --mosaic 0.25 \
  --steps 1500 --threads 2
train-loso: setup    ## issue 55's leave-one-source-out table: a pretrained-start model per left-out source, then bench.eval_detector (~15-25 min a model on 2 cores; a stopped run goes on with `--resume --report DIR`)
	MACROLOC_EXTRAS=dev,train bash scripts/setup.sh
	$(VENV)/$(LOSO) --leave-out fisheye_robot indoor_objects --out out/loso/A --report out/loso/A/report
	$(VENV)/$(LOSO) --leave-out robot_door_detection --out out/loso/C --report out/loso/C/report
	$(VENV)/$(LOSO) --leave-out facades --out out/loso/D --report out/loso/D/report
	$(VENV)/python -m bench.eval_detector --left-out fisheye_robot,indoor_objects=out/loso/A/detector.onnx \
	  --left-out robot_door_detection=out/loso/C/detector.onnx --left-out facades=out/loso/D/detector.onnx \
	  --json out/loso/eval.json

proto: setup         ## regenerate the committed Python from proto/
	$(VENV)/python scripts/gen_proto.py

clean:
	rm -rf .venv .pytest_cache .mypy_cache .ruff_cache
