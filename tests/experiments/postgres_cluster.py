"""A throwaway PostgreSQL server for the team-tracking-server test: Debian's ``initdb`` / ``pg_ctl`` on a data
directory in /tmp, listening on 127.0.0.1 only, with one database for MLflow.

PostgreSQL refuses to run as root (CI containers often are): there the cluster is owned by and runs as the
unprivileged ``nobody`` user, through util-linux's ``setpriv``. Connections are ``trust``-authenticated, which
is safe only because the server listens on loopback for the few seconds of a test.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path

from tests.ports import address_in_use, free_port

UNPRIVILEGED_USER = "nobody"
DATABASE = "mlflow"
ROLE = "mlflow"


def find_bin_dir() -> Path | None:
    """The directory holding ``initdb``, ``pg_ctl`` and ``createdb``: on PATH, or Debian's versioned
    /usr/lib/postgresql/<major>/bin (the package puts only wrappers on PATH), newest first."""
    on_path = shutil.which("initdb")
    candidates = [Path(on_path).resolve().parent] if on_path else []
    candidates += [Path(p) for p in sorted(glob.glob("/usr/lib/postgresql/*/bin"),
                                           key=lambda p: int(Path(p).parent.name) if Path(p).parent.name.isdigit() else 0,
                                           reverse=True)]
    for folder in candidates:
        if all((folder / tool).is_file() for tool in ("initdb", "pg_ctl", "createdb", "postgres")):
            return folder
    return None


class PostgresCluster:
    """``start()`` initialises and starts the server; ``stop()`` stops it and removes its data directory."""

    def __init__(self, bin_dir: Path):
        self.bin_dir = bin_dir
        self.port = free_port()
        # Not pytest's tmp_path: it is private to its owner, and the server may run as another user.
        self.root = Path(tempfile.mkdtemp(prefix="deepword_pg_"))
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self._as_user: list[str] = []
        if os.geteuid() == 0:
            user = pwd.getpwnam(UNPRIVILEGED_USER)
            os.chown(self.root, user.pw_uid, user.pw_gid)
            self._as_user = ["setpriv", f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}", "--clear-groups"]
        self.started = False

    @property
    def uri(self) -> str:
        """SQLAlchemy URI of the MLflow database (driver: psycopg 3)."""
        return f"postgresql+psycopg://{ROLE}@127.0.0.1:{self.port}/{DATABASE}"

    def _run(self, tool: str, *args: str, timeout: float = 120) -> None:
        done = subprocess.run([*self._as_user, str(self.bin_dir / tool), *args], capture_output=True, text=True,
                              timeout=timeout, cwd=self.root)
        if done.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.is_file() else ""
            raise RuntimeError(f"{tool} {' '.join(args)} failed ({done.returncode}):\n{done.stdout}{done.stderr}{log}")

    def start(self) -> PostgresCluster:
        # --no-sync and fsync=off: a test database that is thrown away need not survive a power cut.
        self._run("initdb", "-D", str(self.data), "-U", ROLE, "--auth=trust", "-E", "UTF8", "--no-sync")
        for attempt in range(4):
            options = f"-h 127.0.0.1 -p {self.port} -k {self.root} -c fsync=off -c full_page_writes=off"
            try:
                self._run("pg_ctl", "-D", str(self.data), "-o", options, "-l", str(self.log), "-w", "-t", "60", "start")
                break
            except RuntimeError as error:  # another test's server took the port first: take another
                if attempt == 3 or not address_in_use(str(error)):
                    raise
                self.port = free_port()
        self.started = True
        self._run("createdb", "-h", "127.0.0.1", "-p", str(self.port), "-U", ROLE, DATABASE)
        return self

    def stop(self) -> None:
        if self.started:
            self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")
            self.started = False
        shutil.rmtree(self.root, ignore_errors=True)
