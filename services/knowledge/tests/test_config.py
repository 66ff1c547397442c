from __future__ import annotations

from pathlib import Path

import pytest
from knowledge.__main__ import load_config
from knowledge.config import HistoryRule
from rap_sdk.entry import EntryError


def test_a_yaml_config_sets_history_rules(tmp_path: Path) -> None:
    f = tmp_path / "kb.yaml"
    f.write_text(
        "system: tb4\nbackend: sqlite\nsqlite_path: kb.db\nhistory:\n"
        "  - {pattern: 'scan/**', max_count: 50, max_age_s: 10}\n"
        "  - {pattern: '**', max_count: 1000}\n"
    )
    cfg = load_config(f)
    assert (cfg.system, cfg.backend) == ("tb4", "sqlite")
    assert cfg.history[0] == HistoryRule(pattern="scan/**", max_count=50, max_age_s=10.0)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("backend: mongo\n", "Invalid enum value 'mongo' - at `$.backend`"),
        ("history: [{pattern: '**', max_cnt: 3}]\n", "unknown field `max_cnt`"),
        ("system: [\n", "not valid YAML"),
    ],
)
def test_config_mistakes_name_the_file_and_field(tmp_path: Path, text: str, words: str) -> None:
    f = tmp_path / "kb.yaml"
    f.write_text(text)
    with pytest.raises(EntryError, match=r"kb\.yaml:\d+:\d+: ") as exc:
        load_config(f)
    assert words in str(exc.value)
