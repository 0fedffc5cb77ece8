"""A throw-away PostgreSQL server for tests: initdb in a temporary directory, start, stop.

The server programs come from PostgreSQL's packages (``bash scripts/postgres.sh`` installs
Debian's); without them :func:`postgres_server` fails with the command that installs them.
initdb and postgres refuse to run as root: as root they run as the ``postgres`` user
(created if missing). The server listens on 127.0.0.1 on a free port, with its socket in
the temporary directory, and trusts local connections.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shlex
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

INSTALL = "bash scripts/postgres.sh  (Debian: apt-get install -y postgresql)"


class PostgresUnavailable(RuntimeError):
    """PostgreSQL's server programs are missing or the server does not start."""


def find_bindir() -> Path:
    """The directory holding ``initdb`` and ``pg_ctl`` (PATH, then Debian's layout)."""
    candidates = []
    initdb = shutil.which("initdb")
    if initdb and shutil.which("pg_ctl"):
        candidates.append(Path(initdb).resolve().parent)
    versions = sorted(
        glob.glob("/usr/lib/postgresql/*/bin"),
        key=lambda p: [int(x) if x.isdigit() else x for x in Path(p).parent.name.split(".")],
        reverse=True,
    )
    candidates += [Path(p) for p in versions] + [Path("/usr/local/pgsql/bin")]
    for bindir in candidates:
        if (bindir / "initdb").is_file() and (bindir / "pg_ctl").is_file():
            return bindir
    raise PostgresUnavailable(
        f"PostgreSQL's server programs (initdb, pg_ctl) were not found; install them: {INSTALL}"
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _as_user() -> list[str]:
    """Command prefix that drops root to the ``postgres`` user (empty when not root)."""
    if os.geteuid() != 0:
        return []
    try:
        pwd.getpwnam("postgres")
    except KeyError:
        subprocess.run(
            ["useradd", "--system", "--no-create-home", "--shell", "/bin/sh", "postgres"],
            check=True,
            capture_output=True,
        )
    runuser = shutil.which("runuser")
    return [runuser, "-u", "postgres", "--"] if runuser else ["su", "postgres", "-c"]


def _run(cmd: list[str], prefix: list[str]) -> subprocess.CompletedProcess:
    if prefix[-1:] == ["-c"]:  # su needs one shell string
        cmd = [shlex.join(cmd)]
    return subprocess.run([*prefix, *cmd], capture_output=True, text=True, timeout=120)


def create_database(url: str, name: str) -> str:
    """Create database ``name`` on the server of ``url``; return the URL of the new one."""
    import psycopg2
    import sqlalchemy

    parsed = sqlalchemy.engine.make_url(url)
    conn = psycopg2.connect(
        host=parsed.host, port=parsed.port, user=parsed.username, dbname="postgres"
    )
    try:
        conn.autocommit = True
        with conn.cursor() as cur:
            cur.execute(f'CREATE DATABASE "{name}"')
    finally:
        conn.close()
    return parsed.set(database=name).render_as_string(hide_password=False)


@contextlib.contextmanager
def postgres_server(dbname: str = "optuna") -> Iterator[str]:
    """Start a PostgreSQL server with a database ``dbname``; yield its SQLAlchemy URL.

    Yields
    ------
    str
        ``postgresql+psycopg2://postgres@127.0.0.1:<port>/<dbname>`` (no password).

    Raises
    ------
    PostgresUnavailable
        The programs are missing, or initdb or the server fails (with its log).
    """
    bindir = find_bindir()
    prefix = _as_user()
    # /tmp/pytest-of-root is private to root: the cluster lives in a directory of its own
    root = Path(tempfile.mkdtemp(prefix="gc-pg-"))
    data, log = root / "data", root / "server.log"
    if prefix:
        pw = pwd.getpwnam("postgres")
        os.chown(root, pw.pw_uid, pw.pw_gid)
    port = _free_port()
    initdb = [str(bindir / "initdb"), "-D", str(data), "-U", "postgres", "--auth=trust"]
    options = (
        f"-c listen_addresses=127.0.0.1 -p {port} -k {root} "
        "-c fsync=off -c synchronous_commit=off -c full_page_writes=off"
    )
    pg_ctl = [str(bindir / "pg_ctl"), "-D", str(data), "-w", "-t", "60"]
    started = False
    try:
        init = _run([*initdb, "-E", "UTF8", "--no-sync"], prefix)
        if init.returncode:
            raise PostgresUnavailable(f"initdb failed:\n{init.stdout}\n{init.stderr}")
        start = _run([*pg_ctl, "-o", options, "-l", str(log), "start"], prefix)
        started = start.returncode == 0
        if not started:
            text = log.read_text() if log.exists() else ""
            raise PostgresUnavailable(f"PostgreSQL did not start:\n{start.stderr}\n{text}")
        server = f"postgresql+psycopg2://postgres@127.0.0.1:{port}/postgres"
        yield create_database(server, dbname)
    finally:
        if started:
            _run([*pg_ctl, "-m", "fast", "stop"], prefix)
        shutil.rmtree(root, ignore_errors=True)
