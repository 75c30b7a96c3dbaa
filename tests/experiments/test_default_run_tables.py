"""make compare's tables of the default run in full (stages/tables/default_run.py): the headline's run, every relation
method on both box sources in both domains, the ceiling of the detected boxes, and the detector's AP."""

from __future__ import annotations

from pipeline.runs import RunRecord
from pipeline.tracker import flatten_params
from stages.tables.default_run import default_run_tables
from tests.experiments.pipeline_runs import compose_config

QUICK = {"profile": "quick"}


def _metrics(base: float) -> dict[str, float]:
    m = {}
    for domain, shift in (("", 0.0), ("shift.", -10.0)):
        for i, subset in enumerate(("easy", "hard", "mixed")):
            for method, offset in (("deepword_then_logic", 0.0), ("deepword", -1.0), ("logic", -2.0),
                                   ("relation_oracle", 8.0)):
                m[f"eval.{domain}detected.{method}.{subset}.pair_f1"] = base + shift + offset + i
                m[f"eval.{domain}detected.{method}.{subset}.image_acc"] = 40.0 + i
            m[f"eval.{domain}gt.deepword.{subset}.pair_f1"] = 99.0 + shift / 100
    m |= {"detector.test.ap50.vehicle": 80.0, "detector.test.ap50.wheel": 88.5, "detector.test.ap.vehicle": 48.0,
          "detector.shift.ap50.vehicle": 70.0}
    return m


def test_the_tables_are_the_headlines_run_with_every_method_in_both_domains():
    params = flatten_params(compose_config([]))
    ablation = flatten_params(compose_config(["ablation=no_gat"]))
    runs = [RunRecord("abl", "ablation", 2, ablation, _metrics(10.0), QUICK),       # newest, but not the default
            RunRecord("new", "default", 1, params, _metrics(80.0), {"git_commit": "abcdef0", "seed": "42"} | QUICK),
            RunRecord("old", "default", 0, params, _metrics(50.0), QUICK)]
    (relations, detector), sources = default_run_tables(runs)
    assert sources == {"default_run": "new"}
    rows = {tuple(row[:3]): row[3:] for row in relations.rows}
    assert rows[("in domain", "detected", "`deepword_then_logic` (what ships)")] == [80.0, 81.0, 82.0, 40.0, 41.0, 42.0]
    assert rows[("in domain", "detected", "DeepWORD alone")][:3] == [79.0, 80.0, 81.0]
    ceiling = "*the ground truth's relations on these boxes (the ceiling)*"
    assert rows[("held out", "detected", ceiling)][:3] == [78.0, 79.0, 80.0]
    assert rows[("held out", "ground truth", "DeepWORD")] == [98.9, 98.9, 98.9, None, None, None]
    # a method the run did not log has no row: logic_plus here
    assert not any("logic_plus" in key[2] for key in rows)
    assert [row[0] for row in relations.rows][:5] == ["in domain"] * 5   # the shipped method first, the ceiling last
    assert relations.rows[3][2] == ceiling and relations.rows[4][1] == "ground truth"
    assert "abcdef0" in relations.notes[-1] and "seed 42" in relations.notes[-1]
    det = {row[0]: row[1:] for row in detector.rows}
    assert det["in domain"] == [80.0, 88.5, 48.0, None]
    assert det["held out"] == [70.0, None, None, None]


def test_without_a_default_run_the_tables_say_what_to_run():
    params = flatten_params(compose_config(["ablation=no_gat"]))
    tables, sources = default_run_tables([RunRecord("abl", "ablation", 0, params, _metrics(10.0), QUICK)])
    assert sources == {"default_run": None}
    assert all(not t.rows and "make pipeline" in t.notes[0] for t in tables)
