"""The expected failures (:mod:`bridge.core.errors`): a :class:`UsageError` is one line for a person; a
:class:`Denied` is one too, with an exit status of its own. (How the CLI prints them: tests/repo/test_cli.py and
the integration tests of each tool.)"""

from __future__ import annotations

import pytest

from bridge.core.errors import Denied, UsageError
from bridge.tools.identity import DENIED_EXIT


def test_a_usage_error_is_its_one_line() -> None:
    err = UsageError("cannot reach the Zenoh router at tcp/127.0.0.1:1: is it up?")
    assert str(err) == "cannot reach the Zenoh router at tcp/127.0.0.1:1: is it up?"
    assert isinstance(err, Exception) and not isinstance(err, (ValueError, OSError))


def test_a_denial_is_a_usage_error_with_its_own_exit_status() -> None:
    with pytest.raises(UsageError, match="^denied: identity 'observer'"):  # whoever catches usage errors catches it
        raise Denied("denied: identity 'observer' (role observer) may not engage a robot")
    assert Denied.EXIT == 3 == DENIED_EXIT  # the tools' exit status for a denial (docs/CLI.md)
    assert Denied.EXIT != 2  # told apart from "nobody answered"
