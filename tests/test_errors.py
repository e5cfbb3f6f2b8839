"""vprflow.core.errors: how a bad value is quoted in a message."""

from vprflow.core.errors import short_repr


def test_a_short_value_is_quoted_whole():
    assert short_repr("a.jpg") == "'a.jpg'"
    assert short_repr("a.jpg", quote=False) == "a.jpg"


def test_a_long_value_is_cut_and_says_how_long_it_was():
    value = list(range(1000))
    text = short_repr(value, limit=100)
    assert len(text) <= 100
    assert text.startswith("[0, 1, 2") and text.endswith(f"... ({len(repr(value))} characters)")
