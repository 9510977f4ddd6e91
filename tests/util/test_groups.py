"""ds3d.util.groups."""

from ds3d.util.groups import group_rows, padded_groups


def test_rows_are_grouped_by_key_in_the_order_keys_are_met():
    assert group_rows(["b", "a", "b", "c", "a"]) == {"b": [0, 2], "a": [1, 4], "c": [3]}
    assert list(group_rows(["b", "a"])) == ["b", "a"]


def test_padded_groups_put_small_maps_together_and_a_large_one_apart():
    shapes = [(10, 12), (64, 64), (11, 9), (12, 12), (63, 60)]
    groups = padded_groups(shapes, call_cost=2_000)
    assert sorted(r for rows in groups for r in rows) == list(range(len(shapes)))
    assert all(rows == sorted(rows) for rows in groups)
    assert [0, 2, 3] in groups  # padded to 12 x 12, each under a call's cost
    assert [1] in groups and [4] in groups  # 63 x 60 padded to 64 x 64 would cost more
    assert padded_groups(shapes, call_cost=0) == [[1], [4], [3], [0], [2]]  # no padding at all
    assert len(padded_groups(shapes, call_cost=10**9)) == 1
