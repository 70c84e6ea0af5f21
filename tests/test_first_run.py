"""The first run's compile wait is said in one line, and only when there is a wait."""

import time

import pytest

from commands.first_run import CompileNotice


@pytest.mark.real_time
def test_a_slow_start_is_said_once_and_a_quick_one_not_at_all(capsys):
    with CompileNotice("actuatord", after=0.05):
        time.sleep(0.3)
    slow = capsys.readouterr().err
    with CompileNotice("actuatord", after=0.5):
        pass
    time.sleep(0.7)  # past the moment it would have spoken
    quick = capsys.readouterr().err
    assert slow.count("\n") == 1
    assert slow.startswith("actuatord: compiling") and "first run" in slow
    assert quick == ""
