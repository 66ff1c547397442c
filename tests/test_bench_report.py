"""The benchmark report helpers that write docs/benchmarks.md."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import report


def test_percentiles_by_nearest_rank() -> None:
    xs = list(range(1, 101))
    assert report.pct(xs, 0.5) == 50
    assert report.pct(xs, 0.99) == 99
    assert report.pct([7], 0.99) == 7
    with pytest.raises(ValueError, match="no samples"):
        report.pct([], 0.5)
    s = report.summary_us([1000, 2000, 3000])
    assert (s["p50_us"], s["n"]) == (2.0, 3)


def test_a_section_is_replaced_and_the_rest_kept(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    doc = tmp_path / "benchmarks.md"
    monkeypatch.setattr(report, "DOC", doc)
    report.write_section("a", "first A")
    report.write_section("b", "only B")
    report.write_section("a", "second A")
    text = doc.read_text()
    assert "second A" in text
    assert "first A" not in text
    assert "only B" in text
    assert text.index("<!-- a:begin -->") < text.index("<!-- b:begin -->")
