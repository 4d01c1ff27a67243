"""The names column cut to the terminal's width (``recordings list``'s TOPICS)."""

from __future__ import annotations

from fleetctl.cli.widetable import MIN_LIST_WIDTH, fit_names, table_with_names

TOPICS = [f"/husky1/topic_{i:02d}" for i in range(20)]  # 16 characters each


def test_names_that_fit_are_all_shown() -> None:
    assert fit_names(TOPICS[:2], 40) == "/husky1/topic_00, /husky1/topic_01"
    assert fit_names([], 40) == "-"


def test_names_past_the_width_end_with_how_many_more() -> None:
    cell = fit_names(TOPICS, 50)
    assert cell == "/husky1/topic_00, /husky1/topic_01 +18 more"
    assert len(cell) <= 50
    assert fit_names(TOPICS, 10, "topics") == "20 topics"  # not even one name fits


def test_the_last_name_is_cut_when_only_the_others_fit() -> None:
    # The first two and "+1 more" fit in 43; all three names (52) do not.
    assert fit_names(TOPICS[:3], 43) == "/husky1/topic_00, /husky1/topic_01 +1 more"


def test_the_table_gives_the_names_what_the_other_columns_leave() -> None:
    rows = [("fleet_a.mcap", 123), ("fleet_b.mcap", 4)]
    text = table_with_names(("NAME", "BYTES", "TOPICS"), rows, [TOPICS, TOPICS[:1]], 80)
    assert all(len(line) <= 80 for line in text.splitlines())
    assert "+" in text.splitlines()[1] and text.splitlines()[2].endswith("/husky1/topic_00")
    narrow = table_with_names(("NAME", "BYTES", "TOPICS"), rows, [TOPICS, []], 20)
    assert len(narrow.splitlines()[1]) <= len("fleet_a.mcap  123    ") + MIN_LIST_WIDTH
    full = table_with_names(("NAME", "BYTES", "TOPICS"), rows, [TOPICS, []], None)
    assert ", ".join(TOPICS) in full
