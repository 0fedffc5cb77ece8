#!/usr/bin/env bash
# Make a Compose client available for tests/test_docker.py, which validates
# docker/compose.yaml with `docker compose config` / `docker-compose config` (no Docker engine
# needed). Idempotent: nothing is done when either client answers. Otherwise installs
# Debian's `docker-compose` with apt-get (as root, or through sudo). Exit status 1 when none
# is there and none can be installed.
set -euo pipefail

have_client() {
  { command -v docker >/dev/null 2>&1 && docker compose version >/dev/null 2>&1; } ||
    command -v docker-compose >/dev/null 2>&1
}

if have_client; then
  echo "compose: $( (docker compose version 2>/dev/null || docker-compose version) | head -1)"
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "compose: no client and no apt-get here; install docker compose or docker-compose" >&2
  exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO="sudo -n"
  else
    echo "compose: no client; installing it needs root: sudo apt-get install -y docker-compose" >&2
    exit 1
  fi
fi
echo "compose: installing Debian's docker-compose (apt-get)"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends docker-compose >/dev/null
have_client || { echo "compose: installed, but no client answers" >&2; exit 1; }
echo "compose: $(docker-compose version | head -1)"
