#!/usr/bin/env bash
# Set up jsr on a fresh machine (Python 3.10+ with pip): system library, then the package.
# Safe to run again: it installs only what is missing.
#
# By default the Python packages are installed at the versions jsr is tested with
# (constraints.txt, every package with its exact version), so the figures match CI's.
#   bash scripts/install.sh            # tested versions (constraints.txt)
#   bash scripts/install.sh --latest   # newest versions pyproject.toml allows
# The tested versions need Python 3.11+ (numpy 2.4, scipy 1.17); on 3.10 use --latest.
set -euo pipefail
cd "$(dirname "$0")/.."

constraints=(-c constraints.txt)
for arg in "$@"; do
    case "$arg" in
        --latest) constraints=() ;;
        -h|--help) sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "install.sh: unknown argument '$arg' (use --latest or nothing)" >&2; exit 2 ;;
    esac
done
if [ ${#constraints[@]} -gt 0 ] && ! python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "install.sh: the tested versions (constraints.txt) need Python 3.11+; use --latest" >&2
    exit 2
fi

# Open3D loads libusb-1.0 at import time; minimal Debian/Ubuntu images lack it.
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
    if [ "$(id -u)" = "0" ]; then
        apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0 >/dev/null
    fi
fi

python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore \
    ${constraints[@]+"${constraints[@]}"} -e ".[test]"
