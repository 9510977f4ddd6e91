"""ds3d.util.groups."""

from ds3d.util.groups import group_rows


def test_rows_are_grouped_by_key_in_the_order_keys_are_met():
    assert group_rows(["b", "a", "b", "c", "a"]) == {"b": [0, 2], "a": [1, 4], "c": [3]}
    assert list(group_rows(["b", "a"])) == ["b", "a"]
