"""A command's linear algebra on one BLAS thread unless the environment says how many: on a
busy machine a BLAS spinning a thread per core made the bundle's 5 ms Cholesky take 0.34 s
(`mocap refine` of the demo's session, load 7 on 2 cores: 7.5 s against 12-28 s)."""

import pytest
from threadpoolctl import threadpool_info

from mocap import cli


def blas_threads_inside_a_command(monkeypatch) -> list[int]:
    seen = []

    def run(args):
        seen.extend(pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas")
        return 0

    import mocap.commands.report as command

    monkeypatch.setattr(command, "run", run)
    assert cli.main(["report", "session"]) == 0
    return seen


def test_a_command_runs_on_one_blas_thread(monkeypatch):
    for name in cli.BLAS_THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    seen = blas_threads_inside_a_command(monkeypatch)
    assert seen and all(n == 1 for n in seen)  # numpy's BLAS and scipy's own


@pytest.mark.parametrize("name", cli.BLAS_THREAD_VARIABLES)
def test_a_thread_count_the_user_set_is_left_alone(monkeypatch, name):
    from threadpoolctl import threadpool_limits

    for other in cli.BLAS_THREAD_VARIABLES:
        monkeypatch.delenv(other, raising=False)
    monkeypatch.setenv(name, "2")
    with threadpool_limits(limits=2, user_api="blas"):  # as the variable would have made it at start
        assert all(n == 2 for n in blas_threads_inside_a_command(monkeypatch))
