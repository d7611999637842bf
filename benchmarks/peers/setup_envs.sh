#!/usr/bin/env bash
# Install the peer simulators taxim and tacto, each in its own venv outside the repo
# (default ~/.cache/gelsim-peers, override with GELSIM_PEERS_DIR). Idempotent: an
# existing venv with the right version is kept. Needs network access to PyPI only.
#
#   benchmarks/peers/setup_envs.sh            # both
#   benchmarks/peers/setup_envs.sh taxim      # one
set -euo pipefail

DIR="${GELSIM_PEERS_DIR:-$HOME/.cache/gelsim-peers}"
PY="${PYTHON:-python3.11}"          # the project's Python; both peers are pure-Python wheels
TAXIM_VERSION=1.4.1
TACTO_VERSION=0.0.3
# pyrender 0.1.45 pins PyOpenGL 3.1.0, whose OSMesa module lacks OSMesaCreateContextAttribs (pyrender's
# OSMesa platform fails to import); 3.1.10, the project's version, has it (EGL works with either)
PYOPENGL_VERSION=3.1.10
mkdir -p "$DIR"

have() { [ -x "$DIR/$1/bin/python" ] && "$DIR/$1/bin/python" -c "from importlib.metadata import version as v; import sys; sys.exit(v('$1') != '$2')" 2>/dev/null; }

setup_taxim() {
  if have taxim "$TAXIM_VERSION"; then echo "taxim $TAXIM_VERSION: present in $DIR/taxim"; return; fi
  "$PY" -m venv --clear "$DIR/taxim"
  "$DIR/taxim/bin/pip" install -q --upgrade pip
  # [jax-cpu] pulls plain jax (CPU jaxlib). [torch] needs torchvision + torch-scatter, which do not
  # install here, and [jax] pulls jax[cuda12]: neither is used.
  "$DIR/taxim/bin/pip" install -q "taxim[jax-cpu]==$TAXIM_VERSION"
}

setup_tacto() {
  if have tacto "$TACTO_VERSION"; then echo "tacto $TACTO_VERSION: present in $DIR/tacto"; return; fi
  "$PY" -m venv --clear "$DIR/tacto"
  local pip="$DIR/tacto/bin/pip"
  "$pip" install -q --upgrade pip
  "$pip" install -q "tacto==$TACTO_VERSION"
  # urdfpy (a tacto dependency) pins networkx 2.2, which fails on Python 3.11: upgrade it
  # (pip then warns about urdfpy's pin; tacto's renderer does not use networkx).
  "$pip" install -q "networkx>=3"
  "$pip" install -q "PyOpenGL==$PYOPENGL_VERSION"
  # tacto requires opencv-python (GUI build, needs libGL/X libs); swap in the headless build of the
  # same version. Both own the cv2 package, so remove the GUI one first.
  local cv
  cv="$("$DIR/tacto/bin/python" -c "from importlib.metadata import version; print(version('opencv-python'))" 2>/dev/null || true)"
  if [ -n "$cv" ]; then
    "$pip" uninstall -q -y opencv-python
    "$pip" install -q "opencv-python-headless==$cv"
  fi
  # numpy 2 aliases (np.float, np.infty) are patched at import by run_tacto.py, not in the package.
}

targets=("$@")
[ ${#targets[@]} -eq 0 ] && targets=(taxim tacto)
for t in "${targets[@]}"; do
  case "$t" in
    taxim) setup_taxim ;;
    tacto) setup_tacto ;;
    *) echo "unknown peer '$t'; choose taxim or tacto" >&2; exit 2 ;;
  esac
done
for t in "${targets[@]}"; do
  "$DIR/$t/bin/python" -c "from importlib.metadata import version; print('$t', version('$t'), 'in $DIR/$t')"
done
