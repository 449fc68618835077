# napari-imgreg: two commands do all set-up on a fresh machine.
#   make demo   create .venv, install, run the main job on the sample scene
#   make test   install system packages + test extras, run the suite under Xvfb

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
# napari needs a real X server even in tests (Qt's offscreen platform cannot
# draw Image/Surface layers): Xvfb + Mesa's software GL.
APT_PACKAGES := xvfb xauth libgl1-mesa-dri libegl1 libglx-mesa0 libxcb-icccm4 \
	libxcb-keysyms1 libxcb-xinerama0 libxcb-cursor0 libxkbcommon-x11-0 \
	libxcb-randr0 libxcb-render-util0 libxcb-shape0 libxcb-image0 libdbus-1-3 \
	libfontconfig1

.PHONY: demo test venv system-deps bench clean help

help:
	@echo "make demo   set up and run the demo on the sample outcrop"
	@echo "make test   set up and run the whole test suite (under Xvfb)"
	@echo "make bench  render benchmark on the 1.2 M-triangle scene -> docs/benchmarks.md"

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e ".[all,testing]"
	touch $@

venv: $(VENV)/.installed

# System packages for the GUI tests; skipped when already present or not root.
system-deps:
	@if command -v xvfb-run >/dev/null 2>&1 && [ -e /usr/lib/x86_64-linux-gnu/libxkbcommon-x11.so.0 ]; then \
		echo "system packages present"; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(APT_PACKAGES); \
	else \
		echo "please install (as root): apt-get install $(APT_PACKAGES)"; exit 1; \
	fi

demo: venv
	$(VENV)/bin/napari-imgreg demo --out demo_output

test: system-deps venv
	# One worker per core, at most 4 (each holds a napari viewer and the sample
	# scenes); they share the one Xvfb display.
	xvfb-run -a -s "-screen 0 1600x1000x24" $(PY) -m pytest -q -n auto --maxprocesses 4 --durations=15

bench: venv
	$(PY) benchmarks/bench_render.py --report docs/benchmarks.md

clean:
	rm -rf demo_output .pytest_cache build *.egg-info
