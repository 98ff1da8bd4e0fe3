"""``scripts/benchmark``: run the declared benchmark suite (``config/benchmark.yaml``: named
``scripts/demo`` runs on synthetic worlds and the shared real data) and write its table,
``docs/results.md``. The page holds today's figures only; earlier ones are in git's history."""

from __future__ import annotations

import argparse
import datetime
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass

import yaml

from ..errors import CoopSlamError
from .paths import REPO as _REPO
from .paths import SHARED_DATA, git_commit
from .results_table import LEGEND, table

DEFAULT_SUITE = os.path.join(_REPO, "config", "benchmark.yaml")
DEFAULT_DATA = SHARED_DATA
DEFAULT_PAGE = os.path.join(_REPO, "docs", "results.md")
_NAME = re.compile(r"^[a-z0-9_]+$")
# Options the benchmark sets itself for every run.
_OWN_OPTIONS = ("--out", "--record", "--no-record")


class BenchmarkError(CoopSlamError):
    """A benchmark suite that cannot be run as written (its file, an entry's name or options)."""


@dataclass(frozen=True)
class SuiteEntry:
    """One run of the suite: ``scripts/demo`` with ``demo`` (``{data}``: the shared data folder);
    skipped when the data folder ``needs`` is missing."""

    name: str
    demo: str
    needs: str | None = None

    def demo_args(self, data_dir: str) -> list[str]:
        return shlex.split(self.demo.replace("{data}", data_dir))


def load_suite(path: str) -> list[SuiteEntry]:
    """The suite's entries, checked: unique lower-case names, options the demo can take."""
    try:
        with open(path, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise BenchmarkError(f"cannot read the benchmark suite {path}: {exc}") from None
    items = doc.get("suite") if isinstance(doc, dict) else None
    if not isinstance(items, list) or not items:
        raise BenchmarkError(f"{path}: expected a non-empty list under 'suite:'")
    entries, seen = [], set()
    for k, item in enumerate(items):
        where = f"{path}: suite entry {k + 1}"
        if not isinstance(item, dict) or set(item) - {"name", "demo", "needs"}:
            raise BenchmarkError(f"{where}: expected keys name, demo and optionally needs")
        name, demo, needs = item.get("name"), item.get("demo"), item.get("needs")
        if not isinstance(name, str) or not _NAME.match(name):
            raise BenchmarkError(f"{where}: name must be lower-case letters, digits and '_'")
        if name in seen:
            raise BenchmarkError(f"{where}: name '{name}' is used twice")
        if not isinstance(demo, str) or not demo.strip():
            raise BenchmarkError(f"{where} ({name}): 'demo' must be the demo's options")
        if needs is not None and not isinstance(needs, str):
            raise BenchmarkError(f"{where} ({name}): 'needs' must be a folder name")
        own = [o for o in _OWN_OPTIONS if o in shlex.split(demo)]
        if own:
            raise BenchmarkError(f"{where} ({name}): {', '.join(own)} is set by the benchmark")
        seen.add(name)
        entries.append(SuiteEntry(name, demo, needs))
    return entries


def select(entries: list[SuiteEntry], only: str | None) -> list[SuiteEntry]:
    """The entries named in ``only`` (comma-separated), in suite order; all when None."""
    if not only:
        return entries
    wanted = [n.strip() for n in only.split(",") if n.strip()]
    unknown = sorted(set(wanted) - {e.name for e in entries})
    if unknown:
        raise BenchmarkError(
            f"unknown suite entries {', '.join(unknown)}; the suite has "
            f"{', '.join(e.name for e in entries)}"
        )
    return [e for e in entries if e.name in wanted]


def run_entry(entry: SuiteEntry, data_dir: str, out_dir: str, timeout_s: float) -> int:
    """Run one entry's demo into ``out_dir/<name>`` (output in ``<name>.log``); its exit code."""
    results = os.path.join(out_dir, entry.name)
    cmd = [os.path.join(_REPO, "scripts", "demo"), *entry.demo_args(data_dir)]
    cmd += ["--no-record", "--out", results]
    with open(results + ".log", "w", encoding="utf-8") as log:
        log.write("$ " + shlex.join(cmd) + "\n")
        log.flush()
        try:
            return subprocess.run(
                cmd, stdout=log, stderr=subprocess.STDOUT, timeout=timeout_s, check=False
            ).returncode
        except subprocess.TimeoutExpired:
            log.write(f"\n[benchmark] gave up after {timeout_s:.0f} s\n")
            return 124


def page(folders: list[str], notes: list[str], suite: str) -> str:
    """docs/results.md: the suite's table with how it was made."""
    text = (
        "# Results\n\n"
        f"Generated {datetime.date.today()} at commit {git_commit() or 'unknown'} by "
        "`scripts/benchmark` (the "
        f"suite in `{os.path.relpath(suite, _REPO)}`; each row is a `scripts/demo` run with the "
        f"options in its first column; earlier figures are in this file's git history). "
        f"{LEGEND}\n\n"
    )
    text += table(folders) if folders else "No run finished.\n"
    if notes:
        text += "\n" + "\n".join(f"- {n}" for n in notes) + "\n"
    return text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/benchmark", description=__doc__.split("\n\n")[0])
    p.add_argument("--suite", default=DEFAULT_SUITE, help="suite YAML (default: %(default)s)")
    p.add_argument("--only", help="run only these entries (comma-separated names)")
    p.add_argument("--list", action="store_true", help="list the suite's entries and exit")
    p.add_argument("--data", default=DEFAULT_DATA, help="shared data folder (default: %(default)s)")
    p.add_argument("--out", help="results folder (default: results/benchmark-<date>)")
    p.add_argument(
        "--page", default=DEFAULT_PAGE, help="where to write the table (default: %(default)s)"
    )
    p.add_argument(
        "--table-only", action="store_true", help="tabulate the runs already in --out, run nothing"
    )
    p.add_argument("--timeout", type=float, default=1800.0, help="per run [s] (default: 1800)")
    args = p.parse_args(argv)
    try:
        suite = load_suite(args.suite)
        chosen = select(suite, args.only)
    except BenchmarkError as exc:
        print(f"[benchmark] ERROR: {exc}", file=sys.stderr)
        return 2
    if args.list:
        for e in chosen:
            print(f"{e.name:24s} scripts/demo {e.demo}")
        return 0
    out_dir = args.out or os.path.join(_REPO, "results", f"benchmark-{datetime.date.today()}")
    os.makedirs(out_dir, exist_ok=True)
    from .hosts import unavailable_reason

    no_hosts = unavailable_reason()  # why --hosts entries cannot run here
    have_data = {
        e.name: (e.needs is None or os.path.isdir(os.path.join(args.data, e.needs)))
        and not (no_hosts and "--hosts" in e.demo.split())
        for e in suite
    }
    failed = []
    todo = [] if args.table_only else [e for e in chosen if have_data[e.name]]
    t0 = time.monotonic()
    for k, entry in enumerate(todo):
        step = f"[benchmark] {k + 1}/{len(todo)} {entry.name}"
        print(f"{step}: scripts/demo {entry.demo}", flush=True)
        t_run = time.monotonic()
        rc = run_entry(entry, args.data, out_dir, args.timeout)
        ok = rc == 0 and os.path.isfile(os.path.join(out_dir, entry.name, "report.json"))
        if not ok:
            failed.append(entry.name)
        outcome = "done" if ok else f"FAILED (exit {rc}, see {out_dir}/{entry.name}.log)"
        print(
            f"{step}: {outcome} in {time.monotonic() - t_run:.0f} s "
            f"({time.monotonic() - t0:.0f} s so far)",
            flush=True,
        )
    # The page shows every entry of the suite that has a run in out_dir (--only adds to them).
    rows, notes = [], []
    for e in suite:
        folder = os.path.join(out_dir, e.name)
        if not have_data[e.name]:
            why = no_hosts if "--hosts" in e.demo.split() else f"no `{e.needs}` in the data folder"
            notes.append(f"`{e.name}`: skipped, {why}")
        elif e.name in failed:
            notes.append(f"`{e.name}`: the demo failed")
        elif os.path.isfile(os.path.join(folder, "report.json")):
            rows.append(folder)
        else:
            notes.append(f"`{e.name}`: not run")
    with open(args.page, "w", encoding="utf-8") as fh:
        fh.write(page(rows, notes, args.suite))
    print(f"[benchmark] wrote {args.page}: {len(rows)} of {len(suite)} runs; " + "; ".join(notes))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
