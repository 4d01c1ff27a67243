"""The report's plots: one legend entry per kind of span."""

from __future__ import annotations

from fleetctl.e2e.report import legend_once


def test_a_repeated_span_label_is_kept_on_its_first_span_only() -> None:
    spans = [[1.0, 2.0, "link cut"], [3.0, 4.0, "link cut"], [5.0, 6.0, "replica down"],
             [7.0, 8.0, "link cut"]]
    assert legend_once(spans) == [(1.0, 2.0, "link cut"), (3.0, 4.0, None),
                                  (5.0, 6.0, "replica down"), (7.0, 8.0, None)]


def test_no_spans_give_no_legend_entries() -> None:
    assert legend_once([]) == []
