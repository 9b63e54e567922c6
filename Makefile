# The README's commands. `make demo` and `make test` each set everything up on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# A pinned CPU build here; on a GPU machine pass e.g. TORCH_SPEC="torch" to keep your CUDA build.
TORCH_SPEC ?= torch==2.13.0
# Extra pip arguments for torch, e.g. TORCH_PIP_ARGS=--index-url=https://download.pytorch.org/whl/cpu
# where pip's default index would pick the CUDA build (this workplace's pip config finds a CPU one).
TORCH_PIP_ARGS ?=
# Optional extras installed beside dev and view, e.g. EXTRAS=align for Open3D (`gsc align`'s global
# step; on Linux it loads the system's libusb-1.0) or EXTRAS=cluster,align (.ci/run does).
EXTRAS ?=
comma := ,
STAMP := $(VENV)/.installed-stamp$(if $(EXTRAS),-$(subst $(comma),-,$(EXTRAS)))
JS := tests/js

FUZZ_CASES ?= 10000
# One reader only, e.g. FUZZ_TARGET=recordings (tests/fuzzing.py's targets).
FUZZ_TARGET ?=

.PHONY: install demo picture test test-fast lint format bench fuzz js-deps screenshot clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q $(TORCH_PIP_ARGS) "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e '.[dev,view$(if $(EXTRAS),$(comma)$(EXTRAS))]'
	@# (asked for, Open3D must load: its Linux build needs libusb-1.0, which a bare Debian lacks)
	$(if $(filter align,$(subst $(comma), ,$(EXTRAS))),@$(PY) -c "import open3d" 2>/dev/null || { \
		echo "Open3D cannot load: install libusb-1.0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0)"; exit 1; })
	touch $(STAMP)

install: $(STAMP)

# Independent readers used by the tests (the official TypeScript MCAP reader, splat-transform).
# Skipped only when npm is absent; a failing install fails the target.
js-deps:
	@if command -v npm >/dev/null 2>&1; then \
		if [ ! -d $(JS)/node_modules ] || [ $(JS)/package.json -nt $(JS)/node_modules ]; then \
			npm install --prefix $(JS) --no-audit --no-fund --loglevel=error && touch $(JS)/node_modules; \
		fi; \
	else echo "npm not found: the independent-reader tests will be skipped"; fi

demo: install
	$(PY) examples/demo.py --out demo_out

# The README's picture: robot A's map of the demo room, rendered beside its importance.
picture: install
	test -f demo_out/robot_a.mcap || $(PY) examples/demo.py --out demo_out
	$(VENV)/bin/gsc render demo_out/robot_a.mcap --seq demo_out/synthetic --frames 12:13 \
		--color rgb --color importance --side-by-side -o demo_out/pictures --force
	mkdir -p docs/images
	$(PY) -c "from PIL import Image; Image.open('demo_out/pictures/side_by_side/000012.png').convert('RGB').save('docs/images/map_importance.png', optimize=True)"

# Every test (the README's and CI's command).
test: install js-deps
	$(PY) -m pytest -q

# The tests not marked slow (none runs SLAM or another minutes-long pipeline): a few minutes.
test-fast: install
	$(PY) -m pytest -q -x -m "not slow"

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

format: install
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

bench: install
	$(PY) bench/offline.py

# Structural fuzzing of every reader of untrusted files (the fast part runs in `make test`).
fuzz: install
	nice -n 10 $(PY) tests/fuzzing.py --cases $(FUZZ_CASES) $(if $(FUZZ_TARGET),--target $(FUZZ_TARGET))

# The README's picture of `gsc view`: its browser test (tiny map, headless Chromium), saved.
screenshot: install
	rm -f docs/images/viewer.png
	GSC_VIEW_SCREENSHOT=docs/images/viewer.png GSC_REQUIRE_BROWSER=1 \
		$(PY) -m pytest -q tests/test_view.py -k page_loads
	test -s docs/images/viewer.png

clean:
	rm -rf $(VENV) $(JS)/node_modules build *.egg-info .pytest_cache .mypy_cache .ruff_cache demo_out
