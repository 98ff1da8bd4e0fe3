"""scripts/benchmark: the declared suite is valid, bad suites are refused by name, and the page
holds a row per finished run and a note for every other entry."""

import json
import os

import pytest

from coop_slam.tools import benchmark
from coop_slam.tools.benchmark import BenchmarkError, load_suite, select


def _write_suite(tmp_path, text):
    path = tmp_path / "suite.yaml"
    path.write_text(text)
    return str(path)


def test_the_repositorys_suite_is_runnable_by_the_demo():
    from coop_slam.tools.demo_args import parse_args

    entries = load_suite(benchmark.DEFAULT_SUITE)
    assert len(entries) >= 10
    for entry in entries:
        args = parse_args(entry.demo_args("/data") + ["--no-record", "--out", "/tmp/x"])
        assert (args.scenario is not None) or (args.dataset is not None), entry.name
        if entry.needs:
            assert entry.needs in entry.demo, entry.name


@pytest.mark.parametrize(
    "text, why",
    [
        ("suite: []\n", "non-empty list"),
        ("suite:\n  - {name: a, demo: --scenario team}\n  - {name: a, demo: --scenario revisit}\n",
         "used twice"),
        ("suite:\n  - {name: Team, demo: --scenario team}\n", "lower-case"),
        ("suite:\n  - {name: a, demo: --scenario team --out /x}\n", "--out is set by the bench"),
        ("suite:\n  - {name: a}\n", "demo's options"),
        ("suite:\n  - {name: a, demo: x, data: y}\n", "expected keys"),
    ],
)  # fmt: skip
def test_a_bad_suite_is_refused_naming_the_entry(tmp_path, text, why):
    with pytest.raises(BenchmarkError, match=why):
        load_suite(_write_suite(tmp_path, text))


def test_unknown_names_in_only_are_refused():
    entries = load_suite(benchmark.DEFAULT_SUITE)
    assert [e.name for e in select(entries, "revisit,team")] == ["team", "revisit"]
    with pytest.raises(BenchmarkError, match="unknown suite entries nope"):
        select(entries, "team,nope")


def test_the_page_has_a_row_per_finished_run_and_notes_the_rest(tmp_path, monkeypatch):
    suite = _write_suite(
        tmp_path,
        "suite:\n"
        "  - {name: good, demo: --scenario team}\n"
        "  - {name: bad, demo: --scenario revisit}\n"
        "  - {name: real, demo: '--dataset {data}/nowhere', needs: nowhere}\n",
    )
    ran = []

    def fake_run(entry, data_dir, out_dir, timeout_s):
        ran.append(entry.name)
        if entry.name == "bad":
            return 3
        os.makedirs(os.path.join(out_dir, entry.name))
        with open(os.path.join(out_dir, entry.name, "report.json"), "w") as fh:
            json.dump({"robots": [{"sensor": "rgbd", "ate_rmse_m": 0.004}]}, fh)
        with open(os.path.join(out_dir, entry.name, "run.json"), "w") as fh:
            json.dump({"scenario": "team"}, fh)
        return 0

    monkeypatch.setattr(benchmark, "run_entry", fake_run)
    page = tmp_path / "results.md"
    argv = ["--suite", suite, "--data", str(tmp_path / "data"), "--out", str(tmp_path / "runs")]
    assert benchmark.main(argv + ["--page", str(page)]) == 1  # one run failed
    assert ran == ["good", "bad"]
    text = page.read_text()
    assert "| `--scenario team` |" in text and "| 0.40 |" in text
    assert "`bad`: the demo failed" in text
    assert "`real`: skipped, no `nowhere`" in text
    # Tabulating again runs nothing and keeps the finished run.
    assert benchmark.main(argv + ["--page", str(page), "--table-only"]) == 0
    assert ran == ["good", "bad"] and "| `--scenario team` |" in page.read_text()
    assert "`bad`: not run" in page.read_text()
