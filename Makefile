# make all [SEQ=name]   set up if needed, generate the synthetic row (or use data/raw/SEQ), run every stage
# make test             set up if needed and run the test suite (all but the tests marked slow)
# make test-slow        the tests marked slow (whole rows, campaigns, killed runs, the real recording)
# make <stage> SEQ=...  run one stage (stage names come from pipeline/dag.py)
# make campaign SEQS="a b c" [ARGS="--scheduler ADDRESS --config FILE"]   every row, windows on one cluster
# make track SEQS="row@date1 row@date2 ..." [ARGS="--set track.gate_m=0.04"]   one row's fruits across dates
SEQ ?= synth_row
ARGS ?=
VENV := .venv
PY := $(VENV)/bin/python
PAG := $(VENV)/bin/pag
STAMP := $(VENV)/.installed
# The stage list is declared once, in pipeline/dag.py (importable without the venv).
STAGES := $(shell python3 -c 'from pipeline.dag import STAGE_ORDER; print(*STAGE_ORDER)' 2>/dev/null)

.PHONY: all test test-slow setup bench clean $(sort $(STAGES) evaluate)

all: $(STAMP)
	$(PAG) all --seq $(SEQ) $(ARGS)

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" $(ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow $(ARGS)

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh
	touch $@

$(sort $(STAGES) evaluate): $(STAMP)
	$(PAG) $@ --seq $(SEQ) $(ARGS)

.PHONY: campaign
campaign: $(STAMP)
	$(if $(strip $(SEQS)),,$(error give the rows: make campaign SEQS="row_a row_b ..."))
	$(PAG) campaign --seqs $(SEQS) $(ARGS)

.PHONY: track
track: $(STAMP)
	$(if $(strip $(SEQS)),,$(error give the dates of the row: make track SEQS="row_d1 row_d2 ..."))
	$(PAG) track --seqs $(SEQS) $(ARGS)

bench: $(STAMP)
	$(PAG) bench $(ARGS)

clean:
	rm -rf data/interim/$(SEQ) data/processed/$(SEQ)
