#!/usr/bin/env bash
# Install everything partinspect needs on a fresh Debian machine:
# Chromium for the HTML report's browser test and PostgreSQL's server for the
# shared-database test, then the Python package with its dependencies
# (editable, with the test and PostgreSQL extras) at the versions in constraints.txt.
# Usage: bash scripts/install.sh [--no-browser | --browser-only]
#   --no-browser    skip Chromium (the report's browser test is then skipped)
#   --browser-only  install only Chromium (what tests/reports/test_browser.py runs when it is missing)
#   --browser       accepted for compatibility: Chromium is installed by default
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

apt_install() {
    # $1: a file that tells whether the package is there; the rest: Debian packages.
    local probe=$1; shift
    if [ -e "$probe" ] || ldconfig -p 2>/dev/null | grep -q "$probe"; then
        return 0
    fi
    local sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "install: cannot install $* (no apt-get here); install it with your system's package manager" >&2
        return 1
    fi
    echo "install: installing Debian package(s) $*" >&2
    if ! { $sudo apt-get install -y -q "$@" >/dev/null 2>&1 || { $sudo apt-get update -q >/dev/null 2>&1 && $sudo apt-get install -y -q "$@" >/dev/null 2>&1; }; }; then
        echo "install: could not install Debian package(s) $* (are you root or a sudoer, and is a package mirror reachable?)" >&2
        return 1
    fi
}

browser=yes
case "${1:-}" in
    --no-browser) browser=no ;;
    --browser-only) browser=only ;;
    --browser|"") ;;
    *) echo "install: unknown option $1 (use --no-browser or --browser-only)" >&2; exit 2 ;;
esac

install_browser() {
    # Chromium is only needed by the report's browser test: failing to get it is
    # a warning (that test then skips and says why), never a failed install.
    if ! apt_install /usr/bin/chromium chromium; then
        echo "install: without Chromium, tests/reports/test_browser.py will be skipped" >&2
        return 1
    fi
}

install_postgresql() {
    # The server binaries only serve tests/production/test_postgresql.py (a
    # throwaway cluster on 127.0.0.1): failing to get them is a warning.
    if ! apt_install /usr/lib/postgresql postgresql; then
        echo "install: without PostgreSQL's server, tests/production/test_postgresql.py will be skipped" >&2
        return 1
    fi
}

if [ "$browser" = only ]; then
    install_browser
    exit $?
fi
if [ "$browser" = yes ]; then
    install_browser || true
fi
install_postgresql || true

# Re-install when pyproject.toml or constraints.txt (the tested versions)
# changed since the last install by this Python, or when the installed
# partinspect is another checkout's (a clone installed since, then moved or
# deleted): -I leaves the current folder out of the import path.
stamp=build/.install-stamp
want="$("$PYTHON" -c 'import sys;print(sys.executable)') $(cat pyproject.toml constraints.txt | sha256sum | cut -c1-16)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ] || ! "$PYTHON" -c "import importlib.metadata as m; m.version(\"partinspect\")" >/dev/null 2>&1 \
   || ! "$PYTHON" -I -c 'import pathlib, sys, partinspect; sys.exit(pathlib.Path(partinspect.__file__).resolve().parent != pathlib.Path(sys.argv[1]).resolve())' "$PWD/partinspect" >/dev/null 2>&1 \
   || ! "$PYTHON" -c 'import importlib.util as u,sys; sys.exit(not all(u.find_spec(m) for m in ("cadquery","embreex","cv2","trimesh","pytest","psycopg")))'; then
    echo "install: installing partinspect and its Python dependencies (pip)" >&2
    "$PYTHON" -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[test,postgresql]"
    mkdir -p build && echo "$want" > "$stamp"
fi
command -v inspect >/dev/null 2>&1 || hash -r
command -v pyenv >/dev/null 2>&1 && pyenv rehash >/dev/null 2>&1 || true
# The ellipse fit's compiled kernel: compiled once (10-20 s) and cached beside
# its module, so that the first inspection does not pay for it.
"$PYTHON" -c "from partinspect.vision._kernels import warm; warm()"
