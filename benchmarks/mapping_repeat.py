"""Does feature matching repeat? The same database matched again and again.

The rendered test survey (15 photos, tests/mapping/test_mapping_rendered_survey.py) has its
SIFT features extracted once; then its 105 pairs are matched ``--rounds`` times with one
matcher thread (skyfix's default, ``skyfix map --match-threads 1``) and as many times with
``--threads`` threads (COLMAP's default: all cores), each time from a copy of the database
without matches. A round "differs" when any pair's raw matches differ from those of the
first one-thread round. Both settings run interleaved in one process, so they see the same
machine load; run two copies at once to load it further.

Goal: no one-thread round differs (the pipeline's outputs can only repeat when its matches
do). Exits non-zero when one does. Headline on the last line.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import sqlite3
import sys
import tempfile
import time
from pathlib import Path


def _matches(database: Path) -> dict[int, str]:
    """pair id -> digest of its raw matches (row count and bytes)."""
    with sqlite3.connect(database) as con:
        rows = con.execute("SELECT pair_id, rows, data FROM matches ORDER BY pair_id").fetchall()
    con.close()
    return {pair: f"{n}:{hashlib.sha1(data or b'').hexdigest()}" for pair, n, data in rows}


def _match_once(features_db: Path, work: Path, photos: list, threads: int) -> tuple[dict[int, str], float]:
    from skyfix.mapping import sfm

    db = work / f"match-{threads}.db"
    shutil.copy(features_db, db)
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM matches")
        con.execute("DELETE FROM two_view_geometries")
    con.close()
    start = time.perf_counter()
    sfm.match(db, photos, threads=threads)
    return _matches(db), time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=40, help="matching rounds per setting (default 40)")
    parser.add_argument("--threads", type=int, default=-1, help="the multi-threaded setting (-1: all cores)")
    args = parser.parse_args(argv)

    from skyfix.datasets.survey_scene import make_scene, write_survey
    from skyfix.mapping import sfm
    from skyfix.mapping.photos import load_photos

    with tempfile.TemporaryDirectory(prefix="skyfix-match-repeat-") as tmp:
        work = Path(tmp)
        write_survey(work / "survey", make_scene())
        photos, _ = load_photos(work / "survey")
        features_db = work / "features.db"
        sfm.extract(features_db, work / "survey", photos, threads=2)
        print(f"{len(photos)} rendered photos, features extracted; {os.cpu_count()} cores; "
              f"{args.rounds} rounds each of 1 and {args.threads} matching threads, interleaved", flush=True)
        reference: dict[int, str] | None = None
        differing = {1: 0, args.threads: 0}
        seconds = {1: 0.0, args.threads: 0.0}
        for i in range(args.rounds):
            for threads in (1, args.threads):
                found, s = _match_once(features_db, work, photos, threads)
                seconds[threads] += s
                if reference is None:
                    reference = found
                    continue
                diff = [p for p in reference if found.get(p) != reference[p]]
                if diff:
                    differing[threads] += 1
                    print(f"  round {i} with {threads} thread(s): {len(diff)} of {len(reference)} pairs differ "
                          f"from the first one-thread round", flush=True)
        load = os.getloadavg()[0]
    for threads in differing:
        print(f"{threads:>2} matching thread(s): {differing[threads]} of {args.rounds} rounds differ, "
              f"{seconds[threads] / args.rounds:.2f} s per round")
    ok = differing[1] == 0
    print(f"matching repeat: one thread {differing[1]}/{args.rounds} rounds differ, {args.threads} threads "
          f"{differing[args.threads]}/{args.rounds} (load {load:.1f} at the end): "
          + ("goal met" if ok else "goal NOT MET"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
