from helpers import SHARED_DATA, shared_data


def test_shared_data_index_present():
    p = shared_data("INDEX.md")
    assert p.parent == SHARED_DATA
