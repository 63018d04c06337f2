"""The batch manifest of a session: what each stage read and wrote, by content hash.

``SESSION/batch/manifest.toml`` holds, per stage, its arguments and the SHA-256 of every
file it read and wrote when it last ran. A stage is up to date, and skipped, when its
arguments and the hashes of its inputs are the same as then and its outputs are still the
files it wrote. A file a later stage rewrites in place (sync updates the calibration) is
judged by the hash the chain had at that point, and a copy of it is kept in
``batch/store/<hash>`` so that a stage that must run again reads what it read before.

Hashes of unchanged files (same size and modification time) are taken from the manifest
instead of being computed again, so a re-run does not read every video.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from mocap.io import toml_writer
from mocap.io.atomic import atomic_path, write_text

MANIFEST = Path("batch") / "manifest.toml"
STORE = Path("batch") / "store"
_BLOCK = 1 << 20


@dataclass
class Manifest:
    """stages: {stage name: {"args": [...], "inputs": {file: hash}, "outputs": {file: hash},
    "seconds": float}}; files: {file: [size, mtime_ns, hash]}, the hash cache. File names are
    relative to the session folder where they lie inside it."""

    root: Path
    stages: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)

    @classmethod
    def load(cls, root: Path) -> Manifest:
        path = root / MANIFEST
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except (FileNotFoundError, tomllib.TOMLDecodeError, UnicodeDecodeError):
            return cls(root)  # none yet, or unreadable: every stage runs
        return cls(root, dict(data.get("stages", {})), dict(data.get("files", {})))

    def save(self) -> None:
        write_text(self.root / MANIFEST, toml_writer.dumps({"stages": self.stages, "files": self.files}))

    def key(self, path: Path) -> str:
        """The manifest's name of a file: relative to the session folder if inside it."""
        path = Path(path)
        try:
            return path.resolve().relative_to(self.root.resolve()).as_posix()
        except ValueError:
            return str(path)

    def args_key(self, args) -> list[str]:
        root = str(self.root.resolve())
        return [a.replace(root, ".") for a in args]

    def hash(self, path: Path) -> str | None:
        """SHA-256 of a file, or of a folder's files and names; None if it does not exist."""
        path = Path(path)
        if path.is_dir():
            digest = hashlib.sha256()
            for child in sorted(p for p in path.rglob("*") if p.is_file()):
                digest.update(child.relative_to(path).as_posix().encode() + b"\0" + self.hash(child).encode())
            return digest.hexdigest()
        try:
            stat = path.stat()
        except FileNotFoundError:
            return None
        key = self.key(path)
        cached = self.files.get(key)
        if cached and cached[0] == stat.st_size and cached[1] == stat.st_mtime_ns:
            return cached[2]
        digest = hashlib.sha256()
        with open(path, "rb") as fh:
            while block := fh.read(_BLOCK):
                digest.update(block)
        self.files[key] = [stat.st_size, stat.st_mtime_ns, digest.hexdigest()]
        return digest.hexdigest()

    def record(self, name: str, args, inputs: dict[str, str], outputs: dict[str, str], seconds: float) -> None:
        self.stages[name] = {"args": self.args_key(args), "inputs": inputs, "outputs": outputs,
                             "seconds": round(seconds, 3)}

    def merge(self, other: Manifest, names) -> None:
        """Take the records of stages `names` (and the hash cache) from `other`."""
        for name in names:
            if name in other.stages:
                self.stages[name] = other.stages[name]
        self.files.update(other.files)

    # --- the store of files a later stage rewrites ----------------------------------------
    def keep(self, path: Path, digest: str) -> None:
        target = self.root / STORE / digest
        if not target.exists():
            with atomic_path(target) as tmp:
                shutil.copyfile(path, tmp)

    def restore(self, path: Path, digest: str) -> bool:
        """Put back the content of hash `digest` at `path`; False if the store lacks it."""
        source = self.root / STORE / digest
        if not source.is_file():
            return False
        with atomic_path(path) as tmp:
            shutil.copyfile(source, tmp)
        os.utime(path)
        return True
