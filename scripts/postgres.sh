#!/usr/bin/env bash
# Make PostgreSQL's server programs (initdb, pg_ctl, postgres) available: the tests start a
# throw-away cluster with them (tests/pg.py) for the multi-worker Optuna study. Quick and
# idempotent: nothing is done when they are already installed (on PATH, or Debian's
# /usr/lib/postgresql/<version>/bin). Otherwise installs Debian's `postgresql` with apt-get
# (as root, or through sudo). Exit status 1 when they are missing and cannot be installed.
set -euo pipefail

find_bindir() {
  local d
  if command -v initdb >/dev/null 2>&1 && command -v pg_ctl >/dev/null 2>&1; then
    dirname "$(command -v initdb)"
    return 0
  fi
  for d in $(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V -r) /usr/local/pgsql/bin; do
    if [ -x "$d/initdb" ] && [ -x "$d/pg_ctl" ]; then
      echo "$d"
      return 0
    fi
  done
  return 1
}

if bindir=$(find_bindir); then
  echo "postgresql: $("$bindir/pg_ctl" --version) in $bindir"
  exit 0
fi

if ! command -v apt-get >/dev/null 2>&1; then
  echo "postgresql: not found and no apt-get here; install PostgreSQL's server (initdb, pg_ctl)" >&2
  exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO="sudo -n"
  else
    echo "postgresql: not found; installing it needs root: sudo apt-get install -y postgresql" >&2
    exit 1
  fi
fi
echo "postgresql: installing Debian's postgresql (apt-get)"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends postgresql >/dev/null
bindir=$(find_bindir) || { echo "postgresql: installed, but initdb/pg_ctl not found" >&2; exit 1; }
echo "postgresql: $("$bindir/pg_ctl" --version) in $bindir"
