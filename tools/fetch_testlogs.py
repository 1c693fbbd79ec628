"""Fetch the public PX4 test logs of tests/testlogs.py into the private cache and check their blob ids.

    python tools/fetch_testlogs.py [--dest DIR]

Each file comes from the repository's mirror where there is one (``$ROTORTWIN_MIRRORS``, default /work/.mirror,
``owner+name/repo`` as the session tool ``fetch github:owner/name`` leaves it; read by blob id with ``git cat-file``),
else from ``https://raw.githubusercontent.com/<repo>/<commit>/<path>``, and is kept only when its ``git hash-object``
equals the listed blob id.  Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from testlogs import TESTLOGS, cache_dir  # noqa: E402


def blob_id(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def from_mirror(repo: str, blob: str) -> bytes | None:
    """The blob from the repository's local mirror, or None where there is no mirror or it lacks the blob."""
    git_dir = Path(os.environ.get("ROTORTWIN_MIRRORS", "/work/.mirror")) / repo.replace("/", "+") / "repo"
    if not git_dir.is_dir():
        return None
    r = subprocess.run(["git", "--git-dir", str(git_dir), "cat-file", "blob", blob], capture_output=True)
    return r.stdout if r.returncode == 0 else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dest", type=Path, default=None, help="cache folder (default: the tests' cache)")
    a = ap.parse_args(argv)
    dest = a.dest or cache_dir()
    dest.mkdir(parents=True, exist_ok=True)
    bad = 0
    for name, (repo, commit, path, blob) in TESTLOGS.items():
        out = dest / f"{blob}.ulg"
        if out.is_file() and blob_id(out.read_bytes()) == blob:
            print(f"{name}: present")
            continue
        url = f"https://raw.githubusercontent.com/{repo}/{commit}/{path}"
        data = from_mirror(repo, blob)
        if data is None:
            try:
                data = urllib.request.urlopen(url, timeout=60).read()
            except OSError as exc:
                print(f"{name}: {url}: {exc} (and no mirror holds blob {blob[:10]}: fetch github:{repo})",
                      file=sys.stderr)
                bad += 1
                continue
        if blob_id(data) != blob:
            print(f"{name}: {url}: blob {blob_id(data)} is not the listed {blob}", file=sys.stderr)
            bad += 1
            continue
        out.write_bytes(data)
        print(f"{name}: {out}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
