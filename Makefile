# The two commands a newcomer runs (see README): `make demo` and `make test`.
# Both create ./.venv on first use and install the toolkit into it.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
DEMO ?= demo

.PHONY: demo test setup serve clean distclean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -e '.[test]'
	touch $@

setup: $(VENV)/.installed

test: setup
	$(BIN)/python -m pytest -q

# The demo's own few-minute training run proves that training works; the motion it shows comes
# from the model shipped with the package (sarah_models/pretrained: ~125 CPU-minutes of the same
# training, scripts/pretrained_fixture_model.sh), on a window of fixtures it never saw: it trained
# on seed 0, whose sessions come out with the same motion and voices whatever their count. The
# shipped model's clip is then exported for Blender and game engines (BVH, glTF, SMPL-X parameters).
demo: setup
	$(BIN)/sarah-fixtures $(DEMO)/raw --sessions 5 --seconds 60 --seed 7
	$(BIN)/sarah-prep $(DEMO)/raw $(DEMO)/shards
	$(BIN)/sarah-train --stage all --config tiny --shards $(DEMO)/shards --out $(DEMO)/runs/tiny --resume --replace-changed
	$(BIN)/sarah-generate --run $(DEMO)/runs/tiny --shards $(DEMO)/shards --split test --gaze 0.8 --no-animation --out $(DEMO)/generated-own-run
	$(BIN)/sarah-generate --pretrained fixture-tiny --shards $(DEMO)/shards --split test --gaze 0.8 --out $(DEMO)/generated
	$(BIN)/sarah-export $(DEMO)/generated/motion.npz --out $(DEMO)/export

# The live agent on the shipped model: prints the page's URL (Ctrl-C stops).
serve: setup
	$(BIN)/sarah-serve --pretrained fixture-tiny

# The demo's outputs only; the virtual environment (several GB) stays: `make distclean` removes it.
clean:
	rm -rf $(DEMO)

distclean: clean
	rm -rf $(VENV)
