#!/usr/bin/env bash
# Placeholder until the comms work lands: installs plain pyzmq (no drafts).
set -euo pipefail
VENV=${1:-.venv}
"$VENV/bin/python" -m pip install -q pyzmq
