"""The ± of training's report (train/report.py ``_ms``): the spread of a metric over splits is the
sample standard deviation - the splits are a sample of the ways the fabrics could be split. The
population one (ddof 0) understated it by a factor sqrt((n-1)/n): 11 % at 5 splits."""

from __future__ import annotations

import math

import numpy as np

from vs2t_edge.train.report import _ms


def test_the_spread_over_splits_is_the_sample_standard_deviation():
    values = [0.90, 0.92, 0.95, 0.88, 0.97]  # five splits' shares
    sd = float(np.std(100 * np.asarray(values), ddof=1))
    assert _ms(values) == f"{100 * np.mean(values):.1f} ± {sd:.1f}"


def test_one_split_has_no_spread_and_nan_splits_are_left_out():
    assert _ms([0.9]) == "90.0"  # one split: a mean, no spread (ddof 1 of one value is undefined)
    assert _ms([0.9, math.nan]) == "90.0"
    assert _ms([0.9, 0.8, math.nan]) == f"85.0 ± {np.std([90.0, 80.0], ddof=1):.1f}"
    assert _ms([]) == "-" and _ms([math.nan]) == "-"


def test_every_table_of_mean_and_spread_uses_the_same_sample_sd():
    """Training's ZSL tables (train/run.py), the comparison's (train/compare.py) and the real-sensor
    check's summary (train/real_check.py) say ± as the report does: one rule, train/stats.py."""
    from vs2t_edge.train import compare, real_check, run

    values = [0.62, 0.70, 0.55, 0.81, 0.66]
    sd = float(np.std(values, ddof=1))
    assert math.isclose(run._stat(values)["std"], 100 * sd)
    assert math.isclose(compare._ms(values)["std"], sd)
    folds = [{"accuracy": {k: v for k in real_check.ACCURACY_KEYS}, "auroc": {k: [v, None] for k in real_check.AUROC_KEYS}}
             for v in values]
    summary = real_check.summarise(folds)
    for key in (*(f"accuracy_{k}" for k in real_check.ACCURACY_KEYS), *(f"auroc_{k}" for k in real_check.AUROC_KEYS)):
        assert math.isclose(summary[key]["std"], sd), key
    assert run._stat([0.5])["std"] == 0.0  # one split: no spread measured
