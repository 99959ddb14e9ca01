"""The thread pool of the data set-up (`gear_nerfstudio.parallel`): results in order, failures stop it."""

from __future__ import annotations

import threading

import pytest

from gear_nerfstudio.parallel import available_cores, run_parallel


def test_results_come_in_the_order_of_the_jobs_whatever_order_they_finish_in():
    first_may_finish = threading.Event()

    def first():
        assert first_may_finish.wait(timeout=10), "the second job never ran beside the first"
        return "first"

    def second():
        first_may_finish.set()  # the first job finishes only after this one has run
        return "second"

    finished = []
    assert run_parallel([first, second], workers=2, done=lambda: finished.append(len(finished))) == ["first", "second"]
    assert finished == [0, 1]


def test_a_failing_job_stops_the_jobs_not_started_and_its_error_is_raised():
    ran = []

    def job(name):
        def run():
            ran.append(name)
            if name == "broken":
                raise ValueError("frame 7 of cam03.mp4 is damaged")
            return name

        return run

    with pytest.raises(ValueError, match="cam03.mp4"):
        run_parallel([job("ok"), job("broken"), job("never")], workers=1, done=lambda: None)
    assert ran == ["ok", "broken"]


def test_available_cores_is_at_least_one():
    assert available_cores() >= 1
