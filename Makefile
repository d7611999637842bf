# Set-up is two commands on a fresh Debian machine with Python 3.11:
#   make demo   - install into .venv (once), then generate the quick dataset and train a first model on it
#   make test   - install into .venv (once), then run the default test suite
# A second run does no reinstall work: installation is keyed on a stamp file
# that depends on pyproject.toml and this Makefile.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
PY     := $(VENV)/bin/python
# CPU build by default (it is what these machines carry; an unpinned torch pulls
# several GB of CUDA packages). GPU users: make TORCH_SPEC="torch==2.13.0" TORCH_INDEX=...
TORCH_SPEC  ?= torch==2.13.0
TORCH_INDEX ?=
GL_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libosmesa6
STAMP       := $(VENV)/.gelsim-installed
PYOPENGL_SPEC := PyOpenGL==3.1.10
DEMO_OUT    ?= out/demo
DEMO_RUN    ?= $(DEMO_OUT)-run

.PHONY: install demo test test-slow test-extras test-cluster bench gl-libs clean-venv gym ray

install: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@$(MAKE) --no-print-directory gl-libs
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH_SPEC)" $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX),)
	$(PY) -m pip install -q -e ".[test]"
	# pyrender 0.1.45 pins PyOpenGL 3.1.0, which cannot make an EGL/OSMesa context on
	# current Mesa; 3.1.10 works and is API compatible (see gelsim/compat.py).
	$(PY) -m pip install -q --no-deps "$(PYOPENGL_SPEC)"
	@touch $(STAMP)

# Headless GL for the pyrender reference backend. Installed when we are root and
# a library is missing; otherwise the exact command is printed and the fast
# backend (and every test that does not need GL) still works.
gl-libs:
	@missing=""; for lib in libEGL.so.1 libOSMesa.so libgbm.so.1 libGL.so.1; do \
	  ldconfig -p 2>/dev/null | grep -q "$$lib" || missing="$$missing $$lib"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing headless GL ($$missing missing)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(GL_PACKAGES) >/dev/null; \
	  else \
	    echo "headless GL missing ($$missing); install it with:"; \
	    echo "  sudo apt-get install -y $(GL_PACKAGES)"; \
	  fi; \
	fi

# Optional: Gymnasium, for gelsim.envs (GraspEnv); without it those tests skip. Reinstalling the
# package lets pip put pyrender's PyOpenGL pin back, so the working PyOpenGL is restored after it.
gym: $(STAMP)
	$(PY) -m pip install -q -e ".[gym]"
	$(PY) -m pip install -q --no-deps "$(PYOPENGL_SPEC)"

# Optional: Ray, for `gelsim generate --ray` and `stam experiment --ray` (docs/scale.md); without it
# the local worker pool is used and the Ray tests skip. Same PyOpenGL restore as for gym.
ray: $(STAMP)
	$(PY) -m pip install -q -e ".[ray]"
	$(PY) -m pip install -q --no-deps "$(PYOPENGL_SPEC)"

# The quick dataset (a demo made by older code, after a `git pull`, is renamed to $(DEMO_OUT).stale-N, not
# deleted), pictures of one of its sequences, then a first model: stam's quick config trained on it and
# evaluated on its test split (docs/quickstart.md has the times; a rerun reuses the pretrained backbone).
demo: $(STAMP)
	$(VENV)/bin/gelsim generate --preset quick --replace-stale --out $(DEMO_OUT)
	$(VENV)/bin/gelsim show $(DEMO_OUT)
	$(VENV)/bin/stam train --config quick --data $(DEMO_OUT) --out $(DEMO_RUN)
	$(VENV)/bin/stam evaluate --checkpoint $(DEMO_RUN)/best.pt
	@echo "demo dataset: $(DEMO_OUT) (manifest.json, previews/); model: $(DEMO_RUN) (best.pt, eval-test.json, confusion-test.png)"

# The default suite, then the wheel test (tests/test_install.py, about 2 min): a wheel of this tree
# installed into a fresh virtualenv outside the clone makes the quick dataset and runs the README's
# MuJoCo snippet.
test: $(STAMP)
	$(PY) -m pytest -q
	$(PY) -m pytest -q -m install tests/test_install.py

test-slow: $(STAMP)
	$(PY) -m pytest -q -m "slow or not slow"

# The tests that start their own two-node Ray cluster on 127.0.0.1 and torchrun processes.
test-cluster: ray
	$(PY) -m pytest -q -rs -m cluster

# The tests of the optional engines, after installing them (Gymnasium: gelsim.envs; Ray: generation
# and the sweep on Ray, in-process and on a two-node local cluster).
test-extras: gym ray
	$(PY) -m pytest -q -rs tests/gelsim/test_envs.py tests/gelsim/test_ray.py tests/stam/test_experiment_ray.py -m "cluster or not cluster"

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean-venv:
	rm -rf $(VENV)
