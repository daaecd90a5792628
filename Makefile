# Two commands on a fresh machine: `make run SEQ=taekwondo` and `make test`.
# Every target that runs Python first brings the machine up (scripts/bootstrap.sh),
# which is quick when nothing is missing.
SHELL := /bin/bash
PY := .venv/bin/python
SEQ ?= taekwondo
STAGE ?=
WORKERS ?= 2
ARGS ?=

.PHONY: setup run stage test bench reliability lint clean check-seq

setup:
	@bash scripts/bootstrap.sh

# SEQ names a folder of data_samples/ and nothing else.
check-seq:
	@case "$(SEQ)" in ""|*/*|*..*) echo "make: SEQ must be the name of a folder in data_samples/ (got '$(SEQ)')"; exit 2;; esac
	@test -d "data_samples/$(SEQ)" || { echo "make: no sample 'data_samples/$(SEQ)'; available: $$(find data_samples -mindepth 1 -maxdepth 1 -type d -printf '%f\n' | sort | paste -sd ' ' -)"; exit 2; }

run: setup check-seq
	$(PY) -m pipeline run data_samples/$(SEQ) --out runs/$(SEQ) --workers $(WORKERS) $(ARGS)
	@if [ -f data_samples/$(SEQ)/groundtruth/joints.csv ]; then $(PY) -m pipeline eval runs/$(SEQ) | head -3; fi
	@echo "report: runs/$(SEQ)/export/report.html   motion: runs/$(SEQ)/export/ (joints.csv, quality.csv, joints.trc, motion.bvh, joints.c3d, angles.csv)"

stage: setup check-seq
	@test -n "$(STAGE)" || { echo "make: say which stage, e.g. make stage STAGE=tracking SEQ=$(SEQ)"; exit 2; }
	$(PY) -m pipeline run data_samples/$(SEQ) --out runs/$(SEQ) --only $(STAGE) --workers $(WORKERS) $(ARGS)

test:
	@bash scripts/bootstrap.sh --test
	$(PY) -m pytest

bench: setup
	$(PY) -m pipeline bench --out runs/bench $(ARGS)

# Issue #13's battery (bad inputs, kills, corruptions, concurrency) on the tiny sample; exit 1 on a failure.
reliability: setup
	$(PY) scripts/reliability.py $(ARGS)

lint: setup
	.venv/bin/ruff check .

clean: check-seq
	rm -rf "runs/$(SEQ)"
