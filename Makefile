# colf — build, test, demo, man pages, install.
# Everything builds in release mode: candle in debug is ~200x slower, and one profile keeps one
# build cache.

SHELL := /bin/bash
PREFIX ?= /usr/local
CARGO ?= cargo
RELEASE := target/release
BINS := $(patsubst bin/%.rs,%,$(wildcard bin/colf-*.rs))
# The bundled models, installed to PREFIX/share/colf/ (default: trained without labels;
# supervised: trained with weak mask supervision; blender: supervised adapted to Blender's look).
MODELS := models/default.safetensors models/supervised.safetensors models/blender.safetensors
DEMO := out/demo

.PHONY: all build test pyenv lint man demo demo-blender model model-blender data-unsupervised model-unsupervised data-both model-both model-small model-default data-paper model-paper model-paper-wide resume model-room-chair model-room-diverse data-room-chair data-room-diverse model-city demo-city demo-room eval-sheet bench bench-train tradeoff fuzz install uninstall clean

all: build

build:
	$(CARGO) build --release

# The Python the cross-checks run (tests/python/): a project-local virtual environment made
# from tests/python/requirements.txt, remade when that file changes. Nothing is installed into
# the system Python.
PY_ENV := target/py
PYTHON ?= python3
$(PY_ENV)/.installed: tests/python/requirements.txt
	@command -v $(PYTHON) >/dev/null || { echo "make: $(PYTHON) not found (install python3 and python3-venv)" >&2; exit 1; }
	rm -rf $(PY_ENV)
	$(PYTHON) -m venv $(PY_ENV) || { echo "make: '$(PYTHON) -m venv' failed (on Debian: apt-get install python3-venv)" >&2; exit 1; }
	$(PY_ENV)/bin/pip install --quiet --disable-pip-version-check -r tests/python/requirements.txt
	touch $@

pyenv: $(PY_ENV)/.installed

# The test command of the README and of .ci/run: the Rust suite, with the project's Python
# first on PATH for the cross-checks.
test: $(PY_ENV)/.installed
	PATH="$(CURDIR)/$(PY_ENV)/bin:$$PATH" $(CARGO) test --release

# Speed and memory on this machine: a table on stdout, target/bench/bench.json.
bench: build
	$(CARGO) build --release --example bench
	$(RELEASE)/examples/bench --out target/bench/bench.json

# Only the trainer's rows of `make bench` (the decoder part of a step, whole training steps and
# the default encoding, fused and autograd side by side): target/bench/bench-train.json.
bench-train: build
	$(CARGO) build --release --example bench
	$(RELEASE)/examples/bench --train-only --out target/bench/bench-train.json

# The speed/accuracy curve of --adaptive, --prune and resolution on held-out scenes, for the
# model MODEL (default: the bundled one): docs/tradeoff.md (table, with the figure of --adaptive
# at its default ε) and docs/tradeoff.png. 100 scenes (300 frames), one run a frame, one thread:
# 8 minutes on the busy 2-core development machine (2026-11-26); TRADEOFF_SCENES=5 for a quick look.
MODEL ?= models/default.safetensors
TRADEOFF_SCENES ?= 100
TRADEOFF_REPS ?= 1
TRADEOFF_THREADS ?= 1
tradeoff: build
	$(CARGO) build --release --example tradeoff
	RAYON_NUM_THREADS=$(TRADEOFF_THREADS) $(RELEASE)/examples/tradeoff --model $(MODEL) \
	  --scenes $(TRADEOFF_SCENES) --reps $(TRADEOFF_REPS) --md docs/tradeoff.md --png docs/tradeoff.png

# Fuzz every input parser in-process (docs/fuzzing.md): FUZZ_ITERATIONS seeded, structure-aware
# mutations each, under a 4 GiB address-space limit; failing inputs go to target/fuzz/<parser>/.
FUZZ_ITERATIONS ?= 100000
FUZZ_SEED ?= 1
fuzz:
	$(CARGO) build --release --example fuzz
	/usr/bin/time -v $(RELEASE)/examples/fuzz --iterations $(FUZZ_ITERATIONS) --seed $(FUZZ_SEED) \
	  --parser all --corpus-out target/fuzz 2> >(grep -E 'FAIL|error|Maximum resident|Elapsed' >&2)

lint:
	$(CARGO) fmt --check
	$(CARGO) clippy --release --all-targets -- -D warnings

# Regenerate man/*.1 from the clap definitions, then check that groff renders them cleanly
# (-k: the pages are UTF-8, as man itself reads them).
man:
	COLF_UPDATE_MAN=1 $(CARGO) test --release --test man_pages
	@for page in man/*.1; do \
	  out=$$(groff -k -man -ww -z $$page 2>&1); \
	  if [ -n "$$out" ]; then echo "$$page: $$out"; exit 1; fi; \
	done
	@echo "man pages: $(words $(wildcard man/*.1)) rendered without warnings"

# Synthesise a held-out 128² scene, encode its first view (the model's default encoding: the best
# of several tries, refined, then the slots the view does not need dropped: one slot an object),
# move one object (the blue cylinder) and delete another (the large cyan cylinder; the edits name
# them by where they stand), render an orbit of novel 128² views with masks before and after the
# edit, and draw a contact sheet:
#   row 1: the input view, then novel views of the encoded scene
#   row 2: the ground-truth mask of the input view, then the rendered masks (one colour a slot)
#   row 3: the same novel views after the edit;  row 4: their masks
# $(call demo_steps,DIR,SYNTH_FLAGS,MODEL_FLAGS,EDITS[,ORBIT_FLAGS[,SHEET_SCALE]]): the demo's
# steps in DIR; ORBIT_FLAGS (colf-cameras orbit's) default to `--size 64` about the clevr567
# cameras' circle, SHEET_SCALE (the sheet's pixels per image pixel) to 3.
define demo_steps
	@mkdir -p $(1)
	$(RELEASE)/colf-synth $(2) --out $(1)/data --scenes 1 --seed 7 --split test -q --force
	$(RELEASE)/colf-encode $(1)/data/scene_00000/view_000.png $(3) \
	  --camera $(1)/data/scene_00000/transforms.json --prune 0.001 -o $(1)/scene.codes
	$(RELEASE)/colf-edit --inspect $(1)/scene.codes > $(1)/slots.json
	$(RELEASE)/colf-edit $(4) $(1)/scene.codes -o $(1)/edited.codes
	$(RELEASE)/colf-cameras orbit --frames 4 $(if $(5),$(5),--size 64) --start-azimuth 20 -o $(1)/orbit.json
	$(RELEASE)/colf-render $(1)/scene.codes $(3) --cameras $(1)/orbit.json --out $(1)/orbit --masks -q
	$(RELEASE)/colf-render $(1)/edited.codes $(3) --cameras $(1)/orbit.json --out $(1)/edited --masks -q
	$(RELEASE)/colf-sheet --cols 5 --scale $(if $(6),$(6),3) -o $(1)/sheet.png \
	  $(1)/data/scene_00000/view_000.png $(1)/orbit/frame_000{0,1,2,3}.png \
	  $(1)/data/scene_00000/view_000.mask.png $(1)/orbit/frame_000{0,1,2,3}.mask.png \
	  - $(1)/edited/frame_000{0,1,2,3}.png \
	  - $(1)/edited/frame_000{0,1,2,3}.mask.png
	@echo "demo: slots in $(1)/slots.json, renders in $(1)/orbit and $(1)/edited,"
	@echo "      contact sheet $(1)/sheet.png"
endef

demo: build
	$(call demo_steps,$(DEMO),--size 128,,examples/demo-edits.json,--size 128,2)

# The same demo on the same scene rendered by Blender (Cycles; apt-get install blender), encoded,
# edited and rendered with the bundled `blender` model (the supervised model adapted to Blender's
# look without labels: make model-blender). The edit moves the blue cylinder (slot 2 of this
# encoding) and deletes the large cyan one (slots 1 and 5: the encoding gave it a second slot,
# hidden behind it in the input view). The sheet is docs/blender-sheet.png. The small model
# (the default until 2026-11-29) also encodes this scene, less well: it draws the small green
# cylinder blue, and deleting the large cyan one leaves a faint cyan haze (docs/training-log.md,
# run r2).
demo-blender: build
	$(call demo_steps,out/demo-blender,--engine blender,--model blender,examples/demo-blender-edits.json)

# The same demo on a held-out Room-Chair scene at 128² (issue 40) with a room model (ROOM_MODEL,
# make model-room-chair): the red chair nearest the camera deleted and the green one moved to
# the back of the room (examples/demo-room-edits.json names them by where they stand), an orbit
# at the rooms' camera distance and elevation.
ROOM_MODEL ?= $(ROOM_RUN)/room-chair/r128.safetensors
demo-room: build
	test -f $(ROOM_MODEL) || { echo "demo-room: no room model at $(ROOM_MODEL): run make model-room-chair first, or set ROOM_MODEL" >&2; exit 1; }
	$(call demo_steps,out/demo-room,--preset room-chair --size 128,--model $(ROOM_MODEL),examples/demo-room-edits.json,--size 128 --radius 8.5 --elevation 35)

# A contact sheet of held-out scenes (issue 37): per scene a row of its four ground-truth views
# then the model's renders of them (view 0 encoded with the model's default encoding, views 1–3
# novel), and below it a row of their masks (ground truth, then one colour a slot). SHEET_MODEL
# on SHEET_SCENES test scenes at 128² from SHEET_ENGINE (blender, the default, or analytic) with
# SHEET_SYNTH's further colf-synth flags (e.g. --preset room-chair); colf-eval's scores of those
# scenes in $(SHEET_DIR)/eval.json; the sheet is SHEET_OUT.
SHEET_ENGINE ?= blender
SHEET_MODEL ?= models/default.safetensors
SHEET_SCENES ?= 3
SHEET_SYNTH ?=
SHEET_DIR := out/eval-sheet
SHEET_OUT ?= $(SHEET_DIR)/sheet.png
eval-sheet: build
	$(RELEASE)/colf-synth --engine $(SHEET_ENGINE) --split test --size 128 --scenes $(SHEET_SCENES) \
	  $(SHEET_SYNTH) --out $(SHEET_DIR)/data -q --force
	$(RELEASE)/colf-eval --data $(SHEET_DIR)/data --model $(SHEET_MODEL) \
	  --renders $(SHEET_DIR)/renders > $(SHEET_DIR)/eval.json
	$(RELEASE)/colf-sheet --cols 8 --scale 2 -o $(SHEET_OUT) $$(for s in $$(ls $(SHEET_DIR)/data | grep '^scene_'); do \
	  for kind in png mask.png; do \
	    for v in 0 1 2 3; do printf '%s ' $(SHEET_DIR)/data/$$s/view_00$$v.$$kind; done; \
	    for v in 0 1 2 3; do printf '%s ' $(SHEET_DIR)/renders/$${s}_v$$v.$$kind; done; \
	  done; done)
	@echo "eval-sheet: $(SHEET_OUT) (scores in $(SHEET_DIR)/eval.json)"

# The city demo (issue 39): CITY_STREETS held-out city-block streets at 128², each encoded from
# its two context views into one scene (one background, one slot a car: colf-encode matches the
# views' slots); street 0 edited by position (examples/demo-city-edits.json, cars named by the
# line of sight from view 0's camera: the red car of the front row removed, the yellow one turned
# and moved to the other lane) and a drive down the
# street rendered before and after; then every street's cars merged into one scene and lined up
# in the street's four lanes (examples/city_traffic.rs writes the colf-edit script), rendered
# along the same street with its time and peak memory (GNU time) in $(CITY_DEMO)/traffic-time.txt.
# The sheet: row 1 street 0's two context views; rows 2–3 the drive and its masks (one colour a
# slot); row 4 the edited drive; rows 5–6 the merged traffic and its masks. CITY_MODEL: the
# city model (make model-city). 20 streets: the default encoding keeps about 4 slots a street
# (docs/training-log.md, "The city model"), so the merged scene holds 60 or more (81 with the
# final city model, from the streets' 98 cars).
CITY_DEMO := out/demo-city
CITY_STREETS ?= 20
CITY_MODEL ?= $(CITY_RUN)/city.safetensors
CITY_DRIVE := --from 40,0,1.3 --to 108,0,1.3 --look-at 70,0,0.5 --look-at-end 140,0,0.5
demo-city: build
	test -f $(CITY_MODEL) || { echo "demo-city: no city model at $(CITY_MODEL): run make model-city first, or set CITY_MODEL" >&2; exit 1; }
	$(CARGO) build --release --example city_traffic
	@mkdir -p $(CITY_DEMO)
	$(RELEASE)/colf-synth --preset city-block --split test --scenes $(CITY_STREETS) --seed 7 \
	  --size 128 --out $(CITY_DEMO)/data -q --force
	for scene in $(CITY_DEMO)/data/scene_*; do \
	  $(RELEASE)/colf-encode $$scene/view_000.png $$scene/view_001.png --camera $$scene/transforms.json \
	    --model $(CITY_MODEL) -o $(CITY_DEMO)/street_$${scene##*_}.codes || exit 1; \
	done
	$(RELEASE)/colf-edit --inspect $(CITY_DEMO)/street_00000.codes > $(CITY_DEMO)/slots.json
	$(RELEASE)/colf-edit examples/demo-city-edits.json $(CITY_DEMO)/street_00000.codes \
	  -o $(CITY_DEMO)/edited.codes
	$(RELEASE)/colf-cameras line $(CITY_DRIVE) --frames 6 --size 128 -o $(CITY_DEMO)/drive.json
	$(RELEASE)/colf-render $(CITY_DEMO)/street_00000.codes --model $(CITY_MODEL) \
	  --cameras $(CITY_DEMO)/drive.json --out $(CITY_DEMO)/drive --masks -q
	$(RELEASE)/colf-render $(CITY_DEMO)/edited.codes --model $(CITY_MODEL) \
	  --cameras $(CITY_DEMO)/drive.json --out $(CITY_DEMO)/drive-edited --masks -q
	$(RELEASE)/examples/city_traffic $(CITY_DEMO)/street_*.codes > $(CITY_DEMO)/traffic-edits.json
	$(RELEASE)/colf-edit $(CITY_DEMO)/traffic-edits.json $(CITY_DEMO)/street_00000.codes \
	  -o $(CITY_DEMO)/traffic.codes
	$(RELEASE)/colf-cameras line --from -30,0,1.3 --to 100,0,1.3 --look-at 0,0,0.5 \
	  --look-at-end 140,0,0.5 --frames 6 --size 128 -o $(CITY_DEMO)/traffic-drive.json
	/usr/bin/time -f "colf-render, merged streets: %e s wall, %U s user, %M KiB peak memory" \
	  -o $(CITY_DEMO)/traffic-time.txt $(RELEASE)/colf-render $(CITY_DEMO)/traffic.codes \
	  --model $(CITY_MODEL) --cameras $(CITY_DEMO)/traffic-drive.json --out $(CITY_DEMO)/traffic --masks -q
	$(RELEASE)/colf-edit --inspect $(CITY_DEMO)/traffic.codes | grep -c '"index"' \
	  | sed 's/^/slots in the merged scene: /' >> $(CITY_DEMO)/traffic-time.txt
	$(RELEASE)/colf-sheet --cols 6 --scale 2 -o $(CITY_DEMO)/sheet.png \
	  $(CITY_DEMO)/data/scene_00000/view_00{0,1}.png - - - - \
	  $(CITY_DEMO)/drive/frame_000{0,1,2,3,4,5}.png $(CITY_DEMO)/drive/frame_000{0,1,2,3,4,5}.mask.png \
	  $(CITY_DEMO)/drive-edited/frame_000{0,1,2,3,4,5}.png \
	  $(CITY_DEMO)/traffic/frame_000{0,1,2,3,4,5}.png $(CITY_DEMO)/traffic/frame_000{0,1,2,3,4,5}.mask.png
	@cat $(CITY_DEMO)/traffic-time.txt
	@echo "demo-city: renders in $(CITY_DEMO)/{drive,drive-edited,traffic}, contact sheet $(CITY_DEMO)/sheet.png"

# The `supervised` model's recipe (docs/training.md; runs in docs/training-log.md, "The supervised model"; it was the default
# model until the unsupervised one matched it): clevr567 scenes at 64², 100 held
# out; a model with slot frames at the attention centroids, a locality bound, 6 Fourier
# frequencies on the rays and a zero background latent. Stage 1 (2,250 steps, 400 scenes): weak
# mask supervision of the compositor, rays drawn 20 % from objects. Stage 2 (from stage 1,
# 54,000 steps, 400 scenes): adds weak mask supervision of the slot attention; learning rate
# constant to step 45,000, then a half cosine to 3e-5. Stage 3 (from stage 2, 18,000 steps,
# 2,000 scenes, the first 400 being stage 2's): learning rate 1e-4, half cosine from step 10,000
# to 2e-5. Stage 4 (from stage 3, 6,000 steps, the 2,000 scenes): rays drawn uniformly, learning
# rate 5e-5, half cosine from step 3,000 to 1e-5. Stage 5 (from stage 4, 10,000 steps, the
# 2,000 scenes): adds slots that cast shadows, read along the light ([30, 55] degrees);
# learning rate 1e-4, half cosine from step 6,000 to 1e-5. Stage 6 (from stage 5, 12,000 steps,
# the 2,000 scenes): 4 views a scene (the input view and 3 novel ones) of 256 rays each, learning
# rate 5e-5, half cosine from step 4,000 to 5e-6. Re-running `make model` resumes from the
# checkpoints in $(MODEL_RUN) (a stopped run loses nothing; a stage is skipped once the next has
# started). Its default encoding is then set (`colf-train configure`: 12 slots, best of 4 tries,
# 50 refinement steps, the best measured in docs/refinement.md); the result is evaluated on
# the held-out scenes ($(MODEL_RUN)/eval.json with that encoding, eval-fast.json in one pass),
# plotted ($(MODEL_RUN)/training.png) and copied to models/supervised.safetensors.
MODEL_RUN ?= out/model
MODEL_COMMON := --eval-data $(MODEL_RUN)/data/test --checkpoint-every 250 --mask-weight 0.1
STAGE12_FLAGS := $(MODEL_COMMON) --data $(MODEL_RUN)/data/train --eval-every 1000 --eval-scenes 8 \
  --lr 3e-4 --object-fraction 0.2
STAGE34_FLAGS := $(MODEL_COMMON) --data $(MODEL_RUN)/data/train2k --eval-every 2000 \
  --eval-scenes 16 --attention-mask-weight 0.1
# $(call eval_model,RUN,MODEL): MODEL scored on RUN/data/test with its default encoding
# (RUN/eval.json) and in one pass (RUN/eval-fast.json), each written only when complete.
define eval_model
	$(call eval_json,$(1)/data/test,$(2),$(1)/eval.json)
	$(call eval_json,$(1)/data/test,$(2),$(1)/eval-fast.json,--fast)
endef
# $(call eval_json,DATA,MODEL,OUT[,FLAGS]): colf-eval's summary of MODEL on DATA, written to OUT
# only once the evaluation has finished; skipped when OUT already scores MODEL (the same identity:
# a resumed recipe does not score the same model again). Each scene's scores go to a journal
# named by the model's identity as they are done, so an evaluation stopped part way (a room
# set's 100 test scenes take about 100 minutes of a core) continues where it stopped; the
# journal is removed once OUT is written.
eval_json = id=$$($(RELEASE)/colf-train info $(2) | sed -n 's/.*"identity": "\([0-9a-f]*\)".*/\1/p'); \
  grep -qs "\"model\":\"$$id\"" $(3) || \
  { $(RELEASE)/colf-eval --data $(1) --model $(2) $(4) --journal $(3).$$id.journal > $(3).tmp && \
    mv $(3).tmp $(3) && rm -f $(3).$$id.journal; }
# $(call resume_or_init,OUT,INIT): continue OUT's checkpoint if there is one, else start from INIT.
resume_or_init = $(if $(wildcard $(1).ckpt),--resume,--init $(2))
model: build
	@mkdir -p $(MODEL_RUN)
	$(call synth_set,$(MODEL_RUN)/data/train,--scenes 400)
	$(call synth_set,$(MODEL_RUN)/data/train2k,--scenes 2000)
	$(call synth_set,$(MODEL_RUN)/data/test,--scenes 100 --split test)
	test -f $(MODEL_RUN)/stage2.safetensors.ckpt || \
	$(RELEASE)/colf-train $(STAGE12_FLAGS) --out $(MODEL_RUN)/stage1.safetensors \
	  --steps 2250 --warmup 500 --seed 9 \
	  $(if $(wildcard $(MODEL_RUN)/stage1.safetensors.ckpt),--resume,--zero-background \
	  --set ray_fourier_freqs=6 --set attention_frames=true --set fg_locality=2)
	test -f $(MODEL_RUN)/stage3.safetensors.ckpt || \
	$(RELEASE)/colf-train $(STAGE12_FLAGS) --out $(MODEL_RUN)/stage2.safetensors \
	  --steps 54000 --warmup 200 --decay-from 45000 --final-lr 3e-5 --seed 10 \
	  --attention-mask-weight 0.1 \
	  $(call resume_or_init,$(MODEL_RUN)/stage2.safetensors,$(MODEL_RUN)/stage1.safetensors)
	test -f $(MODEL_RUN)/stage4.safetensors.ckpt || \
	$(RELEASE)/colf-train $(STAGE34_FLAGS) --out $(MODEL_RUN)/stage3.safetensors \
	  --object-fraction 0.2 --steps 18000 --lr 1e-4 --warmup 200 --decay-from 10000 \
	  --final-lr 2e-5 --seed 11 \
	  $(call resume_or_init,$(MODEL_RUN)/stage3.safetensors,$(MODEL_RUN)/stage2.safetensors)
	test -f $(MODEL_RUN)/stage6.safetensors.ckpt || \
	$(RELEASE)/colf-train $(STAGE34_FLAGS) --out $(MODEL_RUN)/stage4.safetensors \
	  --object-fraction 0 --steps 6000 --lr 5e-5 --warmup 100 --decay-from 3000 \
	  --final-lr 1e-5 --seed 12 \
	  $(call resume_or_init,$(MODEL_RUN)/stage4.safetensors,$(MODEL_RUN)/stage3.safetensors)
	test -f $(MODEL_RUN)/stage6.safetensors.ckpt || \
	$(RELEASE)/colf-train $(STAGE34_FLAGS) --out $(MODEL_RUN)/stage5.safetensors \
	  --object-fraction 0 --steps 10000 --lr 1e-4 --warmup 100 --decay-from 6000 \
	  --final-lr 1e-5 --seed 23 \
	  $(if $(wildcard $(MODEL_RUN)/stage5.safetensors.ckpt),--resume,--init \
	  $(MODEL_RUN)/stage4.safetensors --set shadow_head=true --set 'shadow_light=[30,55]')
	$(RELEASE)/colf-train $(STAGE34_FLAGS) --out $(MODEL_RUN)/stage6.safetensors \
	  --object-fraction 0 --views 4 --rays 256 --steps 12000 --lr 5e-5 --warmup 100 \
	  --decay-from 4000 --final-lr 5e-6 --seed 24 \
	  $(call resume_or_init,$(MODEL_RUN)/stage6.safetensors,$(MODEL_RUN)/stage5.safetensors)
	$(RELEASE)/colf-train plot $(MODEL_RUN)/stage6.safetensors.log.jsonl -o $(MODEL_RUN)/training.png
	$(RELEASE)/colf-train configure $(MODEL_RUN)/stage6.safetensors \
	  --set 'inference={"slots":12,"tries":4,"refine":50}' -o $(MODEL_RUN)/model.safetensors
	$(call eval_model,$(MODEL_RUN),$(MODEL_RUN)/model.safetensors)
	cp $(MODEL_RUN)/model.safetensors models/supervised.safetensors

# Adaptation to a new look without labels (README, "Train on your own scenes"; docs/training-log.md,
# "Adapting to Blender's CLEVR"): the bundled `supervised` model, trained on colf-synth's analytic scenes,
# fine-tuned on 320 Blender-rendered clevr567 scenes at 64² whose mask files are deleted first,
# so no ground-truth mask can be read (held-out Blender scenes keep theirs, for scoring only).
# 1,500 steps of 4 views x 256 rays, learning rate 5e-5 after 200 warm-up steps, half cosine
# from step 700 to 5e-6 (longer runs lose the decomposition: docs/training-log.md). Held-out scores
# during training come from a validation set (seed 7); the test set is scored at the end.
# Needs Blender (apt-get install blender). Re-running resumes.
ADAPT_RUN ?= out/adapt
model-blender: build
	@mkdir -p $(ADAPT_RUN)
	test -d $(ADAPT_RUN)/data/train || { \
	  $(RELEASE)/colf-synth --engine blender --out $(ADAPT_RUN)/data/train.tmp --scenes 320 -q --resume \
	  && find $(ADAPT_RUN)/data/train.tmp -name '*.mask.png' -delete \
	  && mv $(ADAPT_RUN)/data/train.tmp $(ADAPT_RUN)/data/train; }
	$(call synth_set,$(ADAPT_RUN)/data/val,--engine blender --scenes 32 --seed 7)
	$(call synth_set,$(ADAPT_RUN)/data/test,--engine blender --scenes 100 --split test)
	$(RELEASE)/colf-train --data $(ADAPT_RUN)/data/train --out $(ADAPT_RUN)/blender.safetensors \
	  --views 4 --rays 256 --steps 1500 --lr 5e-5 --warmup 200 --decay-from 700 --final-lr 5e-6 \
	  --seed 31 --eval-data $(ADAPT_RUN)/data/val --eval-every 500 --eval-scenes 16 \
	  --checkpoint-every 250 --keep-every 500 \
	  $(call resume_or_init,$(ADAPT_RUN)/blender.safetensors,models/supervised.safetensors)
	$(RELEASE)/colf-train plot $(ADAPT_RUN)/blender.safetensors.log.jsonl -o $(ADAPT_RUN)/training.png
	$(call eval_model,$(ADAPT_RUN),$(ADAPT_RUN)/blender.safetensors)
	cp $(ADAPT_RUN)/blender.safetensors models/blender.safetensors

# Objects without labels (docs/training-log.md, "Training without labels"): the bundled default
# model. The mask-supervised recipe (make model) from a fresh model, with object proposals
# computed from the images (--proposals) where that recipe reads ground-truth masks. The training
# sets are written without their mask files, so no label can be read; the held-out test scenes
# keep theirs, for scoring only. Stage u1 = the supervised stages 1-2 in one run, 32,000 steps on
# 400 scenes at a constant learning rate, both mask losses on proposals from the start (a longer
# u1 bought nothing: docs/training-log.md); u2-u5 follow the supervised stages 3-6 (2,000 scenes;
# uniform rays; shadows; 4 views a scene), u5 without the compositor's mask loss (the proposals'
# borders are rougher than the objects'). The result gets the same default encoding as the
# supervised model and is scored: $(UNSUP_RUN)/model.safetensors, the analytic-only model that
# make model-both then grows into the small model (make model-small runs both). Re-running
# resumes from the checkpoints in $(UNSUP_RUN). About 7 CPU-hours: run it in the background.
UNSUP_RUN ?= out/unsup
# Extra `--set` overrides of u1's fresh model (make model-paper: the paper's decoder sizes).
UNSUP_SETS ?=
UNSUP_COMMON := --proposals --attention-mask-weight 0.1 \
  --eval-data $(UNSUP_RUN)/data/test --checkpoint-every 250 --keep-every 2000
UNSUP_LATE := $(UNSUP_COMMON) --data $(UNSUP_RUN)/data/train2k --eval-every 2000 --eval-scenes 16
# $(call synth_set,DIR,FLAGS): colf-synth's scenes in DIR, written to DIR.tmp and renamed when
# complete, so a stopped target never leaves a half-made set that the next run would accept;
# the next run continues DIR.tmp where it stopped (--resume).
define synth_set
	test -d $(1) || { $(RELEASE)/colf-synth --out $(1).tmp $(2) -q --resume && mv $(1).tmp $(1); }
endef
# $(call unlabelled_set,DIR,SCENES): colf-synth's training scenes without their mask files.
define unlabelled_set
	test -d $(1) || { $(RELEASE)/colf-synth --out $(1).tmp --scenes $(2) $(3) -q --resume \
	  && find $(1).tmp -name '*.mask.png' -delete && mv $(1).tmp $(1); }
endef
# The recipe's data alone (what make model-paper also trains on).
data-unsupervised: build
	@mkdir -p $(UNSUP_RUN)/data
	$(call unlabelled_set,$(UNSUP_RUN)/data/train,400)
	$(call unlabelled_set,$(UNSUP_RUN)/data/train2k,2000)
	$(call synth_set,$(UNSUP_RUN)/data/test,--scenes 100 --split test)
model-unsupervised: data-unsupervised
	test -f $(UNSUP_RUN)/u2.safetensors.ckpt || \
	$(RELEASE)/colf-train $(UNSUP_COMMON) --mask-weight 0.1 --data $(UNSUP_RUN)/data/train \
	  --out $(UNSUP_RUN)/u1.safetensors --eval-every 1000 --eval-scenes 8 --object-fraction 0.2 \
	  --lr 3e-4 --warmup 500 --steps 32000 --seed 9 \
	  $(if $(wildcard $(UNSUP_RUN)/u1.safetensors.ckpt),--resume,--zero-background \
	  --set ray_fourier_freqs=6 --set attention_frames=true --set fg_locality=2 $(UNSUP_SETS))
	test -f $(UNSUP_RUN)/u3.safetensors.ckpt || \
	$(RELEASE)/colf-train $(UNSUP_LATE) --mask-weight 0.1 --out $(UNSUP_RUN)/u2.safetensors \
	  --object-fraction 0.2 --steps 18000 --lr 1e-4 --warmup 200 --decay-from 10000 \
	  --final-lr 2e-5 --seed 11 \
	  $(call resume_or_init,$(UNSUP_RUN)/u2.safetensors,$(UNSUP_RUN)/u1.safetensors)
	test -f $(UNSUP_RUN)/u4.safetensors.ckpt || \
	$(RELEASE)/colf-train $(UNSUP_LATE) --mask-weight 0.1 --out $(UNSUP_RUN)/u3.safetensors \
	  --object-fraction 0 --steps 6000 --lr 5e-5 --warmup 100 --decay-from 3000 \
	  --final-lr 1e-5 --seed 12 \
	  $(call resume_or_init,$(UNSUP_RUN)/u3.safetensors,$(UNSUP_RUN)/u2.safetensors)
	test -f $(UNSUP_RUN)/u5.safetensors.ckpt || \
	$(RELEASE)/colf-train $(UNSUP_LATE) --mask-weight 0.1 --out $(UNSUP_RUN)/u4.safetensors \
	  --object-fraction 0 --steps 10000 --lr 1e-4 --warmup 100 --decay-from 6000 \
	  --final-lr 1e-5 --seed 23 \
	  $(if $(wildcard $(UNSUP_RUN)/u4.safetensors.ckpt),--resume,--init \
	  $(UNSUP_RUN)/u3.safetensors --set shadow_head=true --set 'shadow_light=[30,55]')
	$(RELEASE)/colf-train $(UNSUP_LATE) --mask-weight 0 --out $(UNSUP_RUN)/u5.safetensors \
	  --object-fraction 0 --views 4 --rays 256 --steps 12000 --lr 5e-5 --warmup 100 \
	  --decay-from 4000 --final-lr 5e-6 --seed 24 \
	  $(call resume_or_init,$(UNSUP_RUN)/u5.safetensors,$(UNSUP_RUN)/u4.safetensors)
	$(RELEASE)/colf-train plot $(UNSUP_RUN)/u5.safetensors.log.jsonl -o $(UNSUP_RUN)/training.png
	$(RELEASE)/colf-train configure $(UNSUP_RUN)/u5.safetensors \
	  --set 'inference={"slots":12,"tries":4,"refine":50}' -o $(UNSUP_RUN)/model.safetensors
	$(call eval_model,$(UNSUP_RUN),$(UNSUP_RUN)/model.safetensors)

# The small model that was the bundled default until 2026-11-29 (identity e7b2d9734a8da004) and
# that make model-paper grows: both recipes, one after the other (about 8 CPU-hours and Blender);
# the result is $(BOTH_RUN)/model.safetensors.
model-small:
	$(MAKE) model-unsupervised
	$(MAKE) model-both

# The bundled default model (issue 37; docs/training.md, "The paper-sized decoder"): p12's
# final model (make model-paper to p11's step 36,000, then make model-paper-wide), its weight
# matrices stored in half precision, with the default encoding chosen within 1.5× the CPU time
# of the small model's (DEFAULT_INFERENCE: 20 refinement steps of 512 rays; docs/refinement.md).
DEFAULT_INFERENCE := {"slots":12,"tries":4,"refine":20,"refine_lr":0.025,"refine_frame_lr":0.015,"refine_rays":512}
model-default: build
	test -f $(PAPER_RUN)/p12-blender128-fast.json || $(MAKE) model-paper-wide
	$(RELEASE)/colf-train configure $(PAPER_RUN)/p12.safetensors --half \
	  --set 'inference=$(DEFAULT_INFERENCE)' -o models/default.safetensors

# One model for both looks, without labels (docs/training-log.md, run r2): the bundled default
# model. The analytic model of `make model-unsupervised` ($(UNSUP_RUN)/model.safetensors) grows a background
# that reads the image (--set background_reader=true) and trains on 600 Blender scenes, 600 of
# its own analytic ones and 400 with a randomised look, all without mask files; object
# proposals feed the attention mask loss, as in u5. Writes $(BOTH_RUN)/model.safetensors and
# scores it on the analytic and the Blender (128²) test scenes (it was the bundled default model
# until 2026-11-29). Needs Blender; re-running resumes.
BOTH_RUN ?= out/both
# Where the result is also copied (empty: nowhere).
BOTH_INSTALL ?=
# The recipe's data alone: Blender, analytic and randomised-look scenes without mask files, the
# Blender validation and 128² test scenes (what make model-paper also trains on).
data-both: data-unsupervised
	@mkdir -p $(BOTH_RUN)/data
	$(call synth_set,$(BOTH_RUN)/data/blender,--engine blender --scenes 600)
	$(call synth_set,$(BOTH_RUN)/data/randomised,--randomize-look --scenes 400 --seed 51)
	$(call synth_set,$(BOTH_RUN)/data/val,--engine blender --scenes 32 --seed 7)
	$(call synth_set,$(BOTH_RUN)/data/test128,--engine blender --scenes 100 --split test --size 128)
	test -d $(BOTH_RUN)/data/mix || scripts/mix_scenes.sh $(BOTH_RUN)/data/mix \
	  b:$(BOTH_RUN)/data/blender:600 a:$(UNSUP_RUN)/data/train2k:600 r:$(BOTH_RUN)/data/randomised:400
model-both: build
	test -f $(UNSUP_RUN)/model.safetensors || { echo "model-both: run make model-unsupervised first" >&2; exit 1; }
	$(MAKE) data-both
	$(RELEASE)/colf-train --data $(BOTH_RUN)/data/mix --out $(BOTH_RUN)/model.safetensors \
	  --proposals --mask-weight 0 --attention-mask-weight 0.1 --object-fraction 0 \
	  --views 4 --rays 256 --steps 5000 --lr 5e-5 --warmup 100 --decay-from 2500 --final-lr 5e-6 \
	  --seed 61 --eval-data $(BOTH_RUN)/data/val --eval-every 1000 --eval-scenes 16 \
	  --checkpoint-every 250 --keep-every 1000 \
	  --lr-scale background_reader.=10 --lr-scale hypernet_bg.fc1.=10 \
	  $(call resume_or_init,$(BOTH_RUN)/model.safetensors,$(UNSUP_RUN)/model.safetensors \
	  --set zero_background=false --set background_reader=true)
	$(call eval_json,$(UNSUP_RUN)/data/test,$(BOTH_RUN)/model.safetensors,$(BOTH_RUN)/analytic64.json)
	$(call eval_json,$(BOTH_RUN)/data/test128,$(BOTH_RUN)/model.safetensors,$(BOTH_RUN)/blender128.json)
	$(if $(BOTH_INSTALL),cp $(BOTH_RUN)/model.safetensors $(BOTH_INSTALL))

# The paper-sized decoder (issue 37; docs/training.md, "The paper-sized decoder"): the small
# model (PAPER_INIT: the bundled default until 2026-11-29) grown to the `paper` preset's decoder
# (light fields 2×256 → 64 features, colour/ordering heads and compositor 3×128; hypernetworks
# 128 wide) without changing what it computes (`colf-train --init` with `--set`,
# src/model/grow.rs: new units start with zero outgoing weights, new layers as the identity),
# then trained on the paper's 128² schedule on a mix of looks without labels. Growing skips the ~88,000 steps of the small model's recipe that
# a fresh paper-sized decoder needs to reach the same point (docs/training-log.md). Runs for days
# on one core: checkpoints, data and logs live in $(PAPER_RUN), outside the work tree, and
# re-running resumes where it stopped (nohup, one thread: see docs/training.md). p12 below
# continues it; make model-default makes the bundled default model of p12's final model.
#
# p11 is p10 (itself run p2's stages p6–p9 in one) with the paper's 128-value slots: each `--set`
# below was added by one of those stages or runs, for the reason given beside it, and grows the
# same from the small model all at once. (The machine lost p9 at step ≈ 22,000 and p10 at step
# ≈ 26,400, both on 2026-11-28; docs/training-log.md.)
PAPER_RUN ?= $(HOME)/colf-runs/paper
# The small model, taken from the repository's history (the last commit that shipped it as
# models/default.safetensors); make model-small trains it again (PAPER_INIT=out/both/model.safetensors).
SMALL_MODEL_COMMIT := 3fa40e0
PAPER_INIT ?= $(PAPER_RUN)/small.safetensors
$(PAPER_RUN)/small.safetensors:
	@mkdir -p $(PAPER_RUN)
	git show $(SMALL_MODEL_COMMIT):models/default.safetensors > $@.tmp || { rm -f $@.tmp; \
	  echo "model-paper: commit $(SMALL_MODEL_COMMIT) is not in this clone: run make model-small and set PAPER_INIT=$(BOTH_RUN)/model.safetensors" >&2; exit 1; }
	mv $@.tmp $@
PAPER_DECODER := --set lfn_hidden=256 --set lfn_features=64 --set head_hidden=128 \
  --set head_hidden_layers=3 --set compositor_hidden=128 --set compositor_hidden_layers=3
# Both hypernetworks 128 wide, the `paper` preset's: every light field a hypernetwork makes is an
# affine function of its H hidden units; latents fitted to all four views of a Blender test scene
# drew it at 28.2 dB, the best point of the 64-wide span at 29.5 dB, free light-field weights at
# 38 dB (`examples/capacity_fit`, docs/training-log.md, twelfth session): the span is what limits.
PAPER_HYPERNET := --set hypernet_hidden=128
# One hidden layer per light-field layer in each hypernetwork (as SIREN's and LFN's: each
# layer's heads read 128 hidden units of their own, the light fields span 3 × 128 dimensions; no
# extra work per ray): on p7's step-8,000 snapshot the best point of that span drew two Blender
# test scenes at 33.3 dB against 32.0 for the shared one (fourteenth session).
PAPER_PER_LAYER := --set hypernet_per_layer=true
# A slot's shadow lines evaluated only within 3 units of it (`shadow_reach`, docs/model.md):
# clevr567's objects and their shadows lie well within, and the far lines were most of the
# shadow work (docs/speed.md).
PAPER_REACH := --set shadow_reach=3
# Each slot evaluated only on the rays that pass within 3 units of its frame origin (`slot_reach`):
# on p8's snapshot three quarters of the slots' light-field evaluations lay beyond, where they
# held weights averaging 7·10⁻⁴; a step takes 0.65–0.70 s instead of 1.0–1.2 (docs/speed.md).
PAPER_SLOT_REACH := --set slot_reach=3
# The paper's 128-value slots, each of the bundled model's 64 values kept twice (src/model/grow.rs):
# latents fitted to two Blender test scenes on p10's step-16,000 snapshot drew them at 30.25 dB,
# and 31.30 with 64 more values reaching the hypernetworks through fixed random weights
# (`examples/capacity_fit --wide-latents 64`, twentieth session): the latent's size held the
# bound down.
PAPER_SLOTS := --set slot_dim=128
PAPER_SETS := $(PAPER_DECODER) $(PAPER_HYPERNET) $(PAPER_PER_LAYER) $(PAPER_REACH) $(PAPER_SLOT_REACH) \
  $(PAPER_SLOTS)
PAPER_LATE := --proposals --mask-weight 0 --attention-mask-weight 0.1 --object-fraction 0 \
  --views 4 --rays 256 --checkpoint-every 250 --keep-every 4000 --eval-every 2000 --eval-scenes 16
PAPER_128 := $(PAPER_RUN)/data128
# The training mix at 128², without mask files: 600 Blender scenes, 600 analytic ones and 400
# analytic ones of varied look and cameras (`--randomize-look --randomize-camera`: floors,
# lights, exposure, noise, camera distance and elevation; docs/synth.md), so that the model does
# not learn colf-synth's one look and camera; 16 Blender validation scenes scored as it trains;
# then the held-out test scenes of both looks, made after the training data so that training
# can start first.
define paper_train_data
	@mkdir -p $(PAPER_128)
	$(call unlabelled_set,$(PAPER_128)/blender,600,--engine blender --size 128)
	$(call unlabelled_set,$(PAPER_128)/analytic,600,--size 128)
	$(call unlabelled_set,$(PAPER_128)/varied,400,--randomize-look --randomize-camera --seed 51 --size 128)
	$(call synth_set,$(PAPER_128)/val,--engine blender --scenes 16 --seed 7 --size 128)
	test -d $(PAPER_128)/mix || scripts/mix_scenes.sh $(PAPER_128)/mix b:$(PAPER_128)/blender:600 \
	  a:$(PAPER_128)/analytic:600 v:$(PAPER_128)/varied:400
endef
define paper_test_data
	$(call synth_set,$(PAPER_128)/test-analytic,--scenes 100 --split test --size 128)
	$(call synth_set,$(PAPER_128)/test-blender,--engine blender --scenes 100 --split test --size 128)
endef
data-paper: build
	$(paper_train_data)
	$(paper_test_data)
# p11: the paper's 60,000 steps at 128² (Adam 5e-5, a half cosine to 5e-6 from step 40,000);
# scored at the end on 100 held-out 128² scenes of each look
# ($(PAPER_RUN)/p11-{analytic,blender}128{,-fast}.json), its curves in $(PAPER_RUN)/training.png.
model-paper: build $(PAPER_INIT)
	$(paper_train_data)
	$(RELEASE)/colf-train $(PAPER_LATE) --data $(PAPER_128)/mix --eval-data $(PAPER_128)/val \
	  --out $(PAPER_RUN)/p11.safetensors --steps 60000 --lr 5e-5 --warmup 200 --decay-from 40000 \
	  --final-lr 5e-6 --seed 83 \
	  $(call resume_or_init,$(PAPER_RUN)/p11.safetensors,$(PAPER_INIT) $(PAPER_SETS))
	$(RELEASE)/colf-train plot $(PAPER_RUN)/p11.safetensors.log.jsonl -o $(PAPER_RUN)/training.png
	$(paper_test_data)
	$(call eval_json,$(PAPER_128)/test-analytic,$(PAPER_RUN)/p11.safetensors,$(PAPER_RUN)/p11-analytic128.json)
	$(call eval_json,$(PAPER_128)/test-analytic,$(PAPER_RUN)/p11.safetensors,$(PAPER_RUN)/p11-analytic128-fast.json,--fast)
	$(call eval_json,$(PAPER_128)/test-blender,$(PAPER_RUN)/p11.safetensors,$(PAPER_RUN)/p11-blender128.json)
	$(call eval_json,$(PAPER_128)/test-blender,$(PAPER_RUN)/p11.safetensors,$(PAPER_RUN)/p11-blender128-fast.json,--fast)

# p12: p11 at step 36,000 with 384-value slots, the 256 new values fresh (`--slot-values fresh`,
# src/model/grow.rs: they start at zero and the hypernetworks read them with fresh weights), then
# the rest of p11's schedule (24,000 steps, the half cosine from p11's step 40,000). Latents
# fitted on p11 stayed at 29.7–30.1 dB from step 12,000 to 28,000, and 256 fresh values fitted
# with them lifted that by 1.25 dB on a frozen decoder (`examples/capacity_fit --wide-latents
# 256`, twenty-third session): 384 values can set each of the three hypernetwork hidden layers'
# 128 units, whose free fit reached 33.2–34.1 dB. Scored as p11 at the end.
P12_INIT ?= $(PAPER_RUN)/p11.step36000.safetensors
P12_SETS := --set slot_dim=384 --slot-values fresh
model-paper-wide: build
	$(paper_train_data)
	test -f $(PAPER_RUN)/p12.safetensors.ckpt || test -f $(P12_INIT) || \
	  { echo "model-paper-wide: no initial model at $(P12_INIT): run make model-paper to p11's step 36,000, or set P12_INIT" >&2; exit 1; }
	$(RELEASE)/colf-train $(PAPER_LATE) --data $(PAPER_128)/mix --eval-data $(PAPER_128)/val \
	  --out $(PAPER_RUN)/p12.safetensors --steps 24000 --lr 5e-5 --warmup 200 --decay-from 4000 \
	  --final-lr 5e-6 --seed 84 \
	  $(call resume_or_init,$(PAPER_RUN)/p12.safetensors,$(P12_INIT) $(P12_SETS))
	$(RELEASE)/colf-train plot $(PAPER_RUN)/p12.safetensors.log.jsonl -o $(PAPER_RUN)/training-p12.png
	$(paper_test_data)
	$(call eval_json,$(PAPER_128)/test-analytic,$(PAPER_RUN)/p12.safetensors,$(PAPER_RUN)/p12-analytic128.json)
	$(call eval_json,$(PAPER_128)/test-analytic,$(PAPER_RUN)/p12.safetensors,$(PAPER_RUN)/p12-analytic128-fast.json,--fast)
	$(call eval_json,$(PAPER_128)/test-blender,$(PAPER_RUN)/p12.safetensors,$(PAPER_RUN)/p12-blender128.json)
	$(call eval_json,$(PAPER_128)/test-blender,$(PAPER_RUN)/p12.safetensors,$(PAPER_RUN)/p12-blender128-fast.json,--fast)

# The long training runs (docs/training.md, "Long runs"), restarted where they stopped: each
# target without a running `make TARGET` is started in the background with the threads its entry
# names (TARGET:LOG[:THREADS], one unless given), its output appended to its log. Run it at the
# start of every session. RESUME_RUNS lists them, e.g. model-room-diverse:$(ROOM_RUN)/room-diverse.log:2
# (a room set on both cores: it must end within the session that starts it, below). None is
# listed now: the room sets ended on 2026-12-02 (scores in docs/results/rooms/;
# docs/training-log.md says how the cores were split).
RESUME_RUNS ?=
resume:
	$(if $(strip $(RESUME_RUNS)),scripts/resume_runs.sh $(RESUME_RUNS),@echo "resume: no long run listed (RESUME_RUNS is empty; docs/training.md, Long runs)")

# Room-Chair and Room-Diverse (issue 40; docs/training.md, "The room models"): the default
# clevr567 model (p12's final model: the paper-sized decoder, 384-value slots, a hidden layer per
# light-field layer in each hypernetwork, shadow lines and slots within 3 units) adapted to each
# room set without labels, the paper's curriculum — 64², then 128² (cut short: below) — on
# unlabelled colf-synth room scenes (the paper's 1,000 and 5,000 training scenes; mask files
# deleted), proposals for the compositor and attention mask losses as in the
# small model's stages u1–u4 (without the compositor's, the background, which reads the image,
# drew the chairs: docs/training-log.md). At the start the model is grown to hypernetworks 256
# wide and floor features (ROOM_WIDE_SETS, below). Held-out: 16 validation scenes (64², then
# 128²) scored as it trains, 100 test scenes at 128² at the end. Data in
# $(ROOM_DATA)/PRESET/data, checkpoints and logs in $(ROOM_RUN)/PRESET, outside the work tree;
# re-running resumes. The 64² stage is 2,000 steps, not the paper's 128,000: a step here costs the
# same at either size (the encoder reads 64² in both stages and a step renders 256 rays a view),
# so 64² steps differ only in their blurred ray targets; the default model was trained at 128²
# already; rp6's 64² validation PSNR was level (23.05–23.41 dB) from step 6,000 to 16,000
# (docs/training-log.md, twenty-third session), its FG-ARI 0.07-0.09 higher at 128², and
# Room-Chair's r64 scored 22.98 dB at step 4,000 and 23.59 at its end, 8,000. The steps go to
# 128², where the targets are scored. The 128² stage is 3,000 steps, not the paper's 90,000:
# every run of it so far was level from its step 2,000-4,000 (validation 22.8-23.1 dB: rp6 to
# step 10,000, r128w to 6,000, r128 to 13,000; docs/training-log.md), 90,000 steps are about 27
# hours of a core, and this machine lost every run in three of the seven sessions from 2026-11-29
# to 2026-12-02 (the last one with Room-Chair's 128² stage at step 15,900 of 20,000), and then in
# every session: a room set's data, both stages and its test scores must end within one session
# (3 hours), so a run takes both cores (make resume's RESUME_RUNS, two threads: 0.7-1.2 s a
# step on 2026-12-02, the machine's CPU shared with others) and one set trains a session. The
# last 500 steps at 64² and 1,000 at 128² decay the rate. Resumed with more --steps, a stage
# continues. Until 2026-12-02 the stages were 8,000 and 20,000 steps, then 4,000 and 8,000 for
# one session.
# Run on both cores (make resume does):
#   RAYON_NUM_THREADS=2 CANDLE_NUM_THREADS=2 nohup make model-room-chair > LOG 2>&1 &
ROOM_DATA ?= $(HOME)/colf-runs/rooms
# A comma inside a $(call) argument.
comma := ,
ROOM_RUN ?= $(HOME)/colf-runs/rooms-p
# Both room sets start from the default model (issue 40: "start from the default clevr567
# model"). Room-Chair started from p11's step-4,000 snapshot until 2026-11-29, when the machine
# lost that run at r128w's step ≈ 10,450 (23.07 dB on its validation scenes at step 6,000).
ROOM_INIT ?= models/default.safetensors
ROOM_COMMON := --proposals --mask-weight 0.1 --attention-mask-weight 0.1 --object-fraction 0 \
  --views 4 --rays 256 --checkpoint-every 250 --keep-every 4000 --eval-every 2000 --eval-scenes 16
# Wider hypernetworks and floor features for the rooms (docs/training-log.md, "The room models",
# twenty-seventh session): on a Room-Chair validation scene, rp6's latents fitted to its four
# views drew them at 24.9 dB and its hypernetworks' free hidden units at 28.1, while free
# light-field weights reached 33.3 (34.0 with floor features): the span of 128 hidden units, not
# the light fields, holds the rooms back, as 64 units held clevr567 back before p7.
ROOM_WIDE_SETS := --set hypernet_hidden=256 --set floor_fourier_freqs=5
# Room-Chair's 128² stage trains the hypernetworks at 5 times its learning rate: at r64's step
# ≈ 4,000 the grown units' outgoing weights were a tenth of the old units' size (mean |w| 0.002
# against 0.015-0.025), so the wider span was hardly used, and 128² trains at 2e-5
# (docs/training-log.md, thirty-fourth session). Until 2026-12-02 that stage ran without it
# (22.90-23.05 dB on the validation scenes from its step 2,000 to 6,000); with it, 22.78 and
# 22.80 at steps 2,000 and 4,000, so Room-Diverse's 128² stage, begun then, runs without it.
ROOM_R128_SETS_room-chair := --lr-scale hypernet_=5
# $(call room_data,PRESET,TRAIN_SCENES): one room preset's data sets (make data-room-chair,
# make data-room-diverse make them ahead, e.g. niced beside a run on the other preset).
define room_data
	@mkdir -p $(ROOM_DATA)/$(1)/data
	$(call unlabelled_set,$(ROOM_DATA)/$(1)/data/train,$(2),--preset $(1))
	$(call unlabelled_set,$(ROOM_DATA)/$(1)/data/train128,$(2),--preset $(1) --size 128)
	$(call synth_set,$(ROOM_DATA)/$(1)/data/val,--preset $(1) --scenes 16 --seed 7)
	$(call synth_set,$(ROOM_DATA)/$(1)/data/val128,--preset $(1) --scenes 16 --seed 7 --size 128)
	$(call synth_set,$(ROOM_DATA)/$(1)/data/test128,--preset $(1) --scenes 100 --split test \
	  --size 128)
endef
# $(call room_model,PRESET,TRAIN_SCENES,SEED): the recipe above for one room preset; the final
# model is $(ROOM_RUN)/PRESET/r128.safetensors.
define room_model
	$(call room_data,$(1),$(2))
	@mkdir -p $(ROOM_RUN)/$(1)
	test -f $(ROOM_RUN)/$(1)/r64.safetensors.ckpt || test -f $(ROOM_INIT) || \
	  { echo "model-$(1): no initial model at $(ROOM_INIT): set ROOM_INIT to a clevr567 model" >&2; exit 1; }
	test -f $(ROOM_RUN)/$(1)/r128.safetensors.ckpt || \
	$(RELEASE)/colf-train $(ROOM_COMMON) --data $(ROOM_DATA)/$(1)/data/train \
	  --eval-data $(ROOM_DATA)/$(1)/data/val --out $(ROOM_RUN)/$(1)/r64.safetensors \
	  --steps 2000 --lr 5e-5 --warmup 200 --decay-from 1500 --final-lr 1e-5 --seed $(3) \
	  $(call resume_or_init,$(ROOM_RUN)/$(1)/r64.safetensors,$(ROOM_INIT) $(ROOM_WIDE_SETS))
	$(RELEASE)/colf-train $(ROOM_COMMON) --data $(ROOM_DATA)/$(1)/data/train128 \
	  --eval-data $(ROOM_DATA)/$(1)/data/val128 --out $(ROOM_RUN)/$(1)/r128.safetensors \
	  --steps 3000 --lr 2e-5 --warmup 100 --decay-from 2000 --final-lr 2e-6 --seed $(3) $(ROOM_R128_SETS_$(1)) \
	  $(call resume_or_init,$(ROOM_RUN)/$(1)/r128.safetensors,$(ROOM_RUN)/$(1)/r64.safetensors)
	$(RELEASE)/colf-train plot $(ROOM_RUN)/$(1)/r64.safetensors.log.jsonl \
	  $(ROOM_RUN)/$(1)/r128.safetensors.log.jsonl --label 64 --label 128 -o $(ROOM_RUN)/$(1)/training.png
	$(call eval_json,$(ROOM_DATA)/$(1)/data/test128,$(ROOM_RUN)/$(1)/r128.safetensors,$(ROOM_RUN)/$(1)/eval-fast.json,--fast)
	$(call eval_json,$(ROOM_DATA)/$(1)/data/test128,$(ROOM_RUN)/$(1)/r128.safetensors,$(ROOM_RUN)/$(1)/eval.json)
endef
model-room-chair: build
	$(call room_model,room-chair,1000,81)
model-room-diverse: build
	$(call room_model,room-diverse,5000,82)
data-room-chair: build
	$(call room_data,room-chair,1000)
data-room-diverse: build
	$(call room_data,room-diverse,5000)

# City-Block (issue 39; docs/training.md, "The city model"): the paper's recipe. c0: a static
# background field pretrained alone on the street (K = 0 slots; the bundled default model's
# image-reading background is discarded for it, its foreground kept). c1 (64²) and c2 (128²):
# the default model's foreground slots on top; the static background cannot draw the cars,
# which differ from scene to scene, so the slots must, and object proposals made against c0's
# render of the street (not labels) tell the mask losses which pixels are cars (the paper: L2
# only; with it the slots took a third of the car pixels in 16,000 steps, docs/training-log.md).
# Unlabelled colf-synth city-block
# scenes (the paper's 500; mask files deleted); held-out: 16 validation scenes as it trains,
# 100 test scenes at 128² at the end, encoded from the two context views and scored on views 2
# and 3. Data, checkpoints and logs in $(CITY_RUN); re-running resumes. One thread:
#   RAYON_NUM_THREADS=1 CANDLE_NUM_THREADS=1 nohup make model-city > LOG 2>&1 &
CITY_RUN ?= $(HOME)/colf-runs/city
# The model the city starts from (c0 keeps its foreground): one that already separates objects.
CITY_INIT ?= models/default.safetensors
CITY_COMMON := --views 4 --rays 256 --checkpoint-every 250 --keep-every 4000 --eval-every 2000 \
  --eval-scenes 16 --seed 91
# The slots' stages (c1, c2) learn the cars from object proposals made against c0's street: what
# a view adds to c0's render of it, in hue, is a car (docs/training.md).
CITY_PROPOSALS := --proposals-against $(CITY_RUN)/c0.safetensors --mask-weight 0.1 \
  --attention-mask-weight 0.1 --object-fraction 0.2
# The test protocol: encoded from the two context views, scored on the two street views.
CITY_EVAL := --input-views 0,1 --novel-views 2,3
# The city model's default encoding adds refinement's mask loss against the proposals
# (docs/refinement.md, "A mask loss against the proposals"), chosen on the 16 validation streets
# with c2 at step 4,750: FG-ARI 0.816 against 0.746 and one slot for 94 % of the cars both
# context views show, against 71 %, for -0.35 dB. The final model, city.safetensors, is c2 with
# it (colf-train configure); c2's own file keeps the colour-only encoding, and both are scored on
# the test streets (eval.json: c2; eval-mask.json: city.safetensors).
CITY_INFERENCE := --set inference.refine_mask=0.3 --set inference.refine_mask_claim=3
CITY_BACKGROUND := --set static_background=true --set zero_background=true --set background_reader=false
# The slots' start (c1; docs/training-log.md, "The city model", eleventh session): the
# background's ordering measured from the nearest car on each ray, not from the world origin,
# which on a street can lie far in front of the cars (c0 has no slots, so it is unaffected);
# each slot placed from its attention on the view's object pixels, at their ground contact; a
# locality bound tight enough that a slot cannot draw the next lane's car; slots more than 2
# units behind a ray's origin culled (a context view's camera stands in front of the other
# row's cars).
CITY_SLOTS := --set background_from_nearest_slot=true --set frames_from_residual=true \
  --set frame_ground_contact=true --set fg_locality=0.5 --set cull_behind=2
# Both context views encoded together in every step (the paper: "two rows of cars (two context
# views)"), so every car has slots of its own and none need draw a car its view does not show.
CITY_CONTEXT := --context-views 0,1
# c2 counts the proposals' unsure pixels within 3 pixels of a car to that car (--mask-claim 3).
# Claiming a 1-pixel ring, the arm c2k won +3.3 points of the car pixels and +0.06 NV-FG-ARI for
# -0.08 dB in 4,000 steps (docs/training-log.md, "The city model", fourteenth session), but a
# lone car still lost its wheels: dark on the dark road, the proposals leave them unsure, and at
# 128² they reach about 5 pixels below the body. With 3 pixels, 9.9 % of the validation streets'
# car pixels stay unsure against 12.8 % with 1 (`colf-train propose --against c0 --claim N`,
# thirtieth session).
CITY_CLAIM := --mask-claim 3
# c1 stops at 8,000 steps at 64² (it was to run 60,000, then 20,000): the street views'
# segmentation was level from step 2,000 to 20,000 (NV-FG-ARI 0.58-0.65) and c1 from p12 drew
# them only 0.23 dB better at step 20,000 than at 8,000 (29.56 against 29.33 dB;
# docs/training-log.md, "The city model"), and the test protocol is at 128², where a car has four
# times the pixels: c2 gets the core sooner.
# c2 runs 10,000 steps at 128² (it was to run 50,000): at its step 7,500 the 100 test streets
# scored FG-ARI 0.838 with the encoding-time mask loss (the issue's target: 0.8), and this machine
# lost ~/colf-runs, and every run in it, in two of the three sessions before 2026-12-01: a run
# that needs five sessions did not finish (docs/training-log.md, "The city model").
model-city: build
	@mkdir -p $(CITY_RUN)/data
	$(call unlabelled_set,$(CITY_RUN)/data/train,500,--preset city-block)
	$(call unlabelled_set,$(CITY_RUN)/data/train128,500,--preset city-block --size 128)
	$(call synth_set,$(CITY_RUN)/data/val,--preset city-block --scenes 16 --seed 7)
	$(call synth_set,$(CITY_RUN)/data/val128,--preset city-block --scenes 16 --seed 7 --size 128)
	$(call synth_set,$(CITY_RUN)/data/test128,--preset city-block --scenes 100 --split test \
	  --size 128)
	test -f $(CITY_RUN)/c1.safetensors.ckpt || \
	$(RELEASE)/colf-train $(CITY_COMMON) --slots 0 --mask-weight 0 --attention-mask-weight 0 \
	  --object-fraction 0 --data $(CITY_RUN)/data/train \
	  --eval-data $(CITY_RUN)/data/val --out $(CITY_RUN)/c0.safetensors \
	  --steps 30000 --lr 1e-3 --warmup 200 --decay-from 20000 --final-lr 1e-4 \
	  $(if $(wildcard $(CITY_RUN)/c0.safetensors.ckpt),--resume,--init $(CITY_INIT) $(CITY_BACKGROUND))
	test -f $(CITY_RUN)/c2.safetensors.ckpt || \
	$(RELEASE)/colf-train $(CITY_COMMON) $(CITY_PROPOSALS) $(CITY_CONTEXT) --data $(CITY_RUN)/data/train \
	  --eval-data $(CITY_RUN)/data/val --out $(CITY_RUN)/c1.safetensors \
	  --steps 4000 --lr 5e-5 --warmup 200 --decay-from 3000 --final-lr 1e-5 \
	  $(call resume_or_init,$(CITY_RUN)/c1.safetensors,$(CITY_RUN)/c0.safetensors) \
	  $(if $(wildcard $(CITY_RUN)/c1.safetensors.ckpt),,$(CITY_SLOTS))
	$(RELEASE)/colf-train $(CITY_COMMON) $(CITY_PROPOSALS) $(CITY_CONTEXT) $(CITY_CLAIM) \
	  --data $(CITY_RUN)/data/train128 --eval-data $(CITY_RUN)/data/val128 --out $(CITY_RUN)/c2.safetensors \
	  --steps 10000 --lr 2e-5 --warmup 100 --decay-from 6000 --final-lr 2e-6 \
	  $(call resume_or_init,$(CITY_RUN)/c2.safetensors,$(CITY_RUN)/c1.safetensors)
	$(RELEASE)/colf-train plot $(CITY_RUN)/c0.safetensors.log.jsonl $(CITY_RUN)/c1.safetensors.log.jsonl \
	  $(CITY_RUN)/c2.safetensors.log.jsonl --label c0 --label c1 --label c2 -o $(CITY_RUN)/training.png
	$(RELEASE)/colf-train configure $(CITY_RUN)/c2.safetensors $(CITY_INFERENCE) -o $(CITY_RUN)/city.safetensors
	$(call eval_json,$(CITY_RUN)/data/test128,$(CITY_RUN)/c2.safetensors,$(CITY_RUN)/eval.json,$(CITY_EVAL))
	$(call eval_json,$(CITY_RUN)/data/test128,$(CITY_RUN)/city.safetensors,$(CITY_RUN)/eval-mask.json,$(CITY_EVAL))

install: build
	install -d $(DESTDIR)$(PREFIX)/bin $(DESTDIR)$(PREFIX)/share/man/man1
	install -m 755 $(addprefix $(RELEASE)/,$(BINS)) $(DESTDIR)$(PREFIX)/bin/
	install -m 644 man/*.1 $(DESTDIR)$(PREFIX)/share/man/man1/
	install -d $(DESTDIR)$(PREFIX)/share/colf
	install -m 644 $(MODELS) $(DESTDIR)$(PREFIX)/share/colf/

uninstall:
	rm -f $(addprefix $(DESTDIR)$(PREFIX)/bin/,$(BINS))
	rm -f $(addprefix $(DESTDIR)$(PREFIX)/share/man/man1/,$(notdir $(wildcard man/*.1)))
	rm -f $(addprefix $(DESTDIR)$(PREFIX)/share/colf/,$(notdir $(MODELS)))

clean:
	$(CARGO) clean
	rm -rf out
