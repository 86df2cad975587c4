import pytest

from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.splits import every_nth, load_split_table, select_views, uniform_subset


def test_llff_protocol_with_known_views():
    table = load_split_table()["llff"]
    split = select_views(20, every_nth(20, table["test_every"]), scene_train_views=table["scenes"]["fern"])
    assert split.train == [6, 13] and split.test == [0, 8, 16]


def test_unknown_counts_are_sampled_uniformly_from_non_test_frames():
    split = select_views(20, every_nth(20), num_train_views=3)
    assert len(split.train) == 3 and not set(split.train) & {0, 8, 16}
    assert split.train == [1, 10, 19]
    assert uniform_subset([1, 2, 3, 4, 5], 1) == [3]


def test_dtu_protocol():
    table = load_split_table()["dtu"]
    excluded = set(table["excluded_from_test"])
    test = [i for i in range(49) if i not in excluded]
    views = {int(k): v for k, v in table["train_views"].items()}
    split = select_views(49, test, num_train_views=4, scene_train_views=views)
    assert split.train == [22, 25, 28, 40] and len(split.test) == 40


def test_explicit_views_win():
    split = select_views(20, every_nth(20), train_views=(3, 5), test_views=(1, 2), scene_train_views={2: [6, 13]})
    assert split.train == [3, 5] and split.test == [1, 2]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"train_views": (3, 25)}, r"train view\(s\) \[25\] do not exist"),
        ({"test_views": (-1,)}, r"test view\(s\) \[-1\] do not exist"),
        ({"train_views": (0, 5)}, r"\[0\] are both training and test views"),
        ({"num_train_views": 30}, "only 17 frames are not test views"),
        ({"num_train_views": 0}, "at least 1"),
        ({"train_views": (3, 3)}, "repeat a view"),
    ],
)
def test_bad_split_options_fail_clearly(kwargs, message):
    with pytest.raises(DataError, match=message):
        select_views(20, every_nth(20), **kwargs)


def test_default_test_can_exclude_training_frames():
    split = select_views(40, every_nth(40), scene_train_views={4: [0, 10, 20, 30]}, num_train_views=4,
                         default_test_excludes_train=True)
    assert split.train == [0, 10, 20, 30] and 0 not in split.test and 8 in split.test
