#!/usr/bin/env bash
# Installs everything Oblique City needs on a fresh Debian/Ubuntu machine with Python 3.11:
# the system library libusb-1.0 (open3d), and the pinned Python packages (editable install of this tree).
# Idempotent: a stamp keyed on pyproject.toml skips the pip step when nothing changed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "setup: installing libusb-1.0 (needed by open3d)"
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

"$PY" - <<'PYEOF'
import sys
if sys.version_info[:2] != (3, 11):
    sys.exit(f"setup: Python 3.11 is required (bpy 5.0.1 wheels), found {sys.version.split()[0]}")
PYEOF

stamp=".setup-stamp"
want=$(sha256sum pyproject.toml | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ] || ! "$PY" -c "import oblique_city.core, bpy, pycolmap, open3d" 2>/dev/null; then
  echo "setup: installing Python packages (pinned in pyproject.toml)"
  "$PY" -m pip install --disable-pip-version-check -q -e ".[blender,dev]"
  echo "$want" > "$stamp"
fi

# cjval, the official CityJSON validator (a Rust program), for the export tests: built once with cargo when cargo is
# there; without it those tests say they were skipped and why.
CJVAL_VERSION=0.10.0
if command -v cargo >/dev/null 2>&1 && ! "${CARGO_HOME:-$HOME/.cargo}/bin/cjval" --version 2>/dev/null | grep -q "$CJVAL_VERSION"; then
  echo "setup: building cjval $CJVAL_VERSION (official CityJSON validator) with cargo"
  cargo install -q --locked cjval --version "$CJVAL_VERSION" --features build-binary \
    || echo "setup: cjval could not be built; the CityJSON validator tests will be skipped"
fi

# gltf-validator, the Khronos glTF validator (npm), for the 3D Tiles tests: installed once where npm is there;
# without it those tests say they were skipped and why.
GLTF_VALIDATOR_VERSION=2.0.0-dev.3.10
GLTF_DIR="${XDG_CACHE_HOME:-$HOME/.cache}/oblique-city/gltf-validator"
if command -v npm >/dev/null 2>&1 && \
    ! grep -qs "\"version\": \"$GLTF_VALIDATOR_VERSION\"" "$GLTF_DIR/node_modules/gltf-validator/package.json"; then
  echo "setup: installing gltf-validator $GLTF_VALIDATOR_VERSION (Khronos glTF validator) with npm"
  mkdir -p "$GLTF_DIR"
  npm install --silent --no-audit --no-fund --prefix "$GLTF_DIR" "gltf-validator@$GLTF_VALIDATOR_VERSION" \
    || echo "setup: gltf-validator could not be installed; the glTF validator test will be skipped"
fi
