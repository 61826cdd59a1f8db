#!/usr/bin/env bash
# Set up jsr on a fresh machine (Python 3.10+ with pip): system library, then the package.
# Safe to run again: it installs only what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

# Open3D loads libusb-1.0 at import time; minimal Debian/Ubuntu images lack it.
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
    if [ "$(id -u)" = "0" ]; then
        apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0 >/dev/null
    fi
fi

python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore -e ".[test]"
