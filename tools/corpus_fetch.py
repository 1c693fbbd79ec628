"""The held-out flight corpus (docs/corpus.md): split it, and fetch it into a cache outside the repo.

    python tools/corpus_fetch.py --split          # compute the tuning/judging halves; write those of the
                                                   # rows without one (a new batch), check all the others
    python tools/corpus_fetch.py [--half H] [--batch B]  # extract every listed flight by its git blob id from
                                                   # the repository mirrors into the cache, checking each sha
    python tools/corpus_fetch.py --check          # only check the cached files' shas

Mirrors: ``$ROTORTWIN_MIRRORS`` (default /work/.mirror), one ``owner+name/repo`` git directory per
repository, as the session tool ``fetch github:owner/name`` leaves them (a script cannot fetch; a
missing mirror is named in one line with the fetch to run).  Cache: ``$ROTORTWIN_CORPUS`` (default
~/.cache/rotortwin/corpus), files ``<half>/<id>.ulg``.  Logs are never written into the repository.

The split rule (fixed; docs/corpus.md): seed 24.  Flights of a vehicle flagged ``holdout_suspect``
(the vehicles issue 24 keeps aside for its own judging) all go to ``judging``.  The other vehicles are
ordered by sha256("24|" + vehicle); within each vehicle the flights are ordered by sha256("24|" + id);
going through that order, flights are dealt alternately to tuning and judging, the alternation carried
from one vehicle to the next, so each vehicle with two or more flights lands in both halves.

Batches: the list grows in batches (column ``batch``; a row without one is batch 1).  The rule is
applied to each batch on its own, the alternation starting afresh, so flights added later never move
an earlier flight from the half it was surveyed in.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import os
import subprocess
import sys
from pathlib import Path

SEED = 24
HALVES = ("tuning", "judging")
ROOT = Path(__file__).resolve().parents[1]
CSV_PATH = ROOT / "docs" / "corpus_flights.csv"


def read_list(path: Path = CSV_PATH) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _h(text: str) -> str:
    return hashlib.sha256(f"{SEED}|{text}".encode()).hexdigest()


def batch_of(row: dict) -> str:
    return row.get("batch") or "1"


def _split_batch(rows: list[dict]) -> dict[str, str]:
    half: dict[str, str] = {}
    by_vehicle: dict[str, list[dict]] = {}
    for r in rows:
        if r["holdout_suspect"] == "1":
            half[r["id"]] = "judging"
        else:
            by_vehicle.setdefault(r["vehicle"], []).append(r)
    turn = 0
    for vehicle in sorted(by_vehicle, key=_h):
        for r in sorted(by_vehicle[vehicle], key=lambda r: _h(r["id"])):
            half[r["id"]] = HALVES[turn % 2]
            turn += 1
    return half


def split(rows: list[dict]) -> dict[str, str]:
    """id -> half, by the fixed rule in the module docstring, applied to each batch on its own."""
    half: dict[str, str] = {}
    for b in sorted({batch_of(r) for r in rows}):
        half.update(_split_batch([r for r in rows if batch_of(r) == b]))
    return half


def git_blob_sha(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def mirror_dir(repository: str) -> Path | None:
    base = Path(os.environ.get("ROTORTWIN_MIRRORS", "/work/.mirror")) / repository.replace("/", "+", 1) / "repo"
    for g in (base / ".git", base):
        if (g / "objects").is_dir():
            return g
    return None


def cache_root() -> Path:
    return Path(os.environ.get("ROTORTWIN_CORPUS", Path.home() / ".cache" / "rotortwin" / "corpus"))


def cache_path(row: dict) -> Path:
    return cache_root() / row["half"] / f"{row['id']}.ulg"


def _extract(row: dict) -> str:
    """Write one flight into the cache; returns a one-line status."""
    dest = cache_path(row)
    if dest.is_file() and git_blob_sha(dest.read_bytes()) == row["blob"]:
        return f"ok (cached) {row['id']}"
    git = mirror_dir(row["repository"])
    if git is None:
        return f"MISSING mirror for {row['id']}: run the session tool `fetch github:{row['repository']}`"
    out = subprocess.run(["git", f"--git-dir={git}", "cat-file", "blob", row["blob"]], capture_output=True)
    if out.returncode != 0:
        return f"MISSING blob {row['blob']} ({row['id']}) in {git}: the mirror lacks it (fetch it again?)"
    if git_blob_sha(out.stdout) != row["blob"]:
        return f"BAD sha for {row['id']}: content does not hash to {row['blob']}"
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".part")
    tmp.write_bytes(out.stdout)
    tmp.replace(dest)
    return f"ok {row['id']} -> {dest}"


def _check(rows: list[dict]) -> int:
    bad = 0
    for r in rows:
        p = cache_path(r)
        if not p.is_file():
            print(f"absent {r['id']} ({p})")
        elif git_blob_sha(p.read_bytes()) != r["blob"]:
            print(f"BAD sha {r['id']} ({p})")
            bad += 1
        else:
            print(f"ok {r['id']}")
    return 1 if bad else 0


def _split_cmd(path: Path) -> int:
    rows = read_list(path)
    want = split(rows)
    if any(not r["half"] for r in rows):  # a new batch: fill its halves, the others are checked
        for r in rows:
            r["half"] = r["half"] or want[r["id"]]
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"wrote halves into {path}")
    wrong = [r["id"] for r in rows if r["half"] != want[r["id"]]]
    for h in HALVES:
        ids = [r["id"] for r in rows if want[r["id"]] == h]
        print(f"{h}: {len(ids)} flights, {len({r['vehicle'] for r in rows if want[r['id']] == h})} vehicles: "
              + " ".join(ids))
    if wrong:
        print(f"{path}: half column differs from the seeded rule for {', '.join(wrong)}")
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--list", type=Path, default=CSV_PATH, help="the corpus list (default docs/corpus_flights.csv)")
    ap.add_argument("--split", action="store_true",
                    help="compute the halves (write those of rows without one, check the others)")
    ap.add_argument("--check", action="store_true", help="only check the shas of cached files")
    ap.add_argument("--half", choices=HALVES, help="only this half")
    ap.add_argument("--batch", help="only this batch (column batch; e.g. 2 to survey a new batch on its own)")
    a = ap.parse_args(argv)
    if a.split:
        return _split_cmd(a.list)
    rows = [r for r in read_list(a.list) if a.half in (None, r["half"]) and a.batch in (None, batch_of(r))]
    if any(not r["half"] for r in rows):
        print(f"{a.list}: no halves yet; run --split first")
        return 2
    if a.check:
        return _check(rows)
    status = [_extract(r) for r in rows]
    print("\n".join(status))
    return 0 if all(s.startswith("ok") for s in status) else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except BrokenPipeError:  # output piped into `head`
        sys.exit(1)
