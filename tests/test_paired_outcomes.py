"""benchmarks/paired_outcomes.py: episode-by-episode counts and the exact McNemar test, against hand counts."""

from __future__ import annotations

import importlib
import math
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def po(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    return importlib.import_module("paired_outcomes")


def test_paired_counts_by_hand(po):
    #          ep: 0    1    2    3    4    5
    ref, row = "SSCTSS", "SCSCTS"
    c = po.paired(ref, row)
    # reference only: ep 1 (C) and 4 (T); row only: ep 2; both fail: ep 3
    assert c == {"collisions": 2, "timeouts": 1, "only_reference": "CT", "only_row": 1, "both_fail": 1,
                 "p": pytest.approx(1.0)}
    with pytest.raises(ValueError, match="3 reference episodes against 2"):
        po.paired("SSS", "SS")


def test_mcnemar_is_the_two_sided_binomial_tail(po):
    assert po.mcnemar_p(0, 0) == 1.0
    assert po.mcnemar_p(0, 5) == pytest.approx(2 / 32)  # 2 * P(X <= 0), X ~ Bin(5, 1/2)
    assert po.mcnemar_p(3, 0) == pytest.approx(0.25)
    assert po.mcnemar_p(7, 17) == pytest.approx(2 * sum(math.comb(24, i) for i in range(8)) / 2 ** 24)
    assert po.mcnemar_p(4, 4) == 1.0  # capped


def test_the_committed_rows_against_orca(po, capsys):
    assert po.main(["gatedgcn_td3_residual_sigma045_s0", "--scenes", "hotel"]) == 0
    out = capsys.readouterr().out
    assert "| hotel | orca | 6 | 0 | | | | |" in out  # ORCA's 6 hotel collisions, its results.json
    assert "| hotel | gatedgcn_td3_residual_sigma045_s0 | 9 | 0 | 3 (CCC) | 0 | 6 | 0.25 |" in out
    with pytest.raises(SystemExit, match="no results for 'nosuch'"):
        po.main(["nosuch"])
