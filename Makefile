# The README's two commands:  make example   and   make test
PYTHON ?= python3
.PHONY: install example test bench

install:
	@bash scripts/install.sh

# Installs everything, then inspects the bundled plate. Exit codes of inspect:
# 0 pass, 1 fail, 3 inconclusive are results; only 2 (the run could not be made) fails make.
example: install
	@$(PYTHON) -m partinspect examples/plate/part.step examples/plate/images/; \
	 code=$$?; echo "inspect exited with $$code (0 pass, 1 fail, 3 inconclusive); report in inspection/report.html"; \
	 test $$code -ne 2

test: install
	$(PYTHON) -m pytest -q

bench: install
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PYTHON) $$b || exit 1; done
