"""Independent solves on threads (estimation/_blas.parallel_map, available_cores): results in order and the
same numbers as one thread, a solve's exception raised to the caller, torch's thread count restored; and the
occupant selection, whose candidates' fits, polishes and profiles run that way, bit for bit the same on one
thread or two."""

from __future__ import annotations

import threading
import time

import pytest
import torch

from conftest import make_foreign
from hybridqcm.estimation import _blas
from hybridqcm.estimation._blas import available_cores, parallel_map
from hybridqcm.estimation.problems import LeastSquaresProblem
from hybridqcm.estimation.response import ExactResponse
from hybridqcm.estimation.solver import build_solver
from hybridqcm.physics.linear_models import SeatBaseExcitation

F64 = torch.float64


def test_results_come_in_order_on_several_threads():
    names = []

    def slow_first(k):  # the first item finishes last
        time.sleep(0.05 * (3 - k))
        names.append(threading.current_thread().name)
        return k * k

    assert parallel_map(slow_first, range(4), 2) == [0, 1, 4, 9]
    assert len(set(names)) == 2  # two threads ran them
    names.clear()
    assert parallel_map(slow_first, range(3), 1) == [0, 1, 4] and set(names) == {threading.main_thread().name}


def test_an_exception_reaches_the_caller_and_torch_threads_are_restored():
    before = torch.get_num_threads()
    inside = []

    def job(k):
        inside.append(torch.get_num_threads())
        if k == 1:
            raise ValueError("sample 1 failed")
        return k

    with pytest.raises(ValueError, match="sample 1 failed"):
        parallel_map(job, range(3), 2)
    assert torch.get_num_threads() == before and set(inside) == {1}  # one intra-op thread per solve meanwhile


def _seat_problems(count: int):
    """``count`` independent seat problems (another seed each): rigid occupants, x0 unknown, 5 % noise."""
    problems = []
    for seed in range(count):
        g = torch.Generator().manual_seed(seed)
        p2 = 200.0 + 600.0 * torch.rand(16, generator=g, dtype=F64)
        truth = torch.cat([torch.stack([0.4 * p2.sqrt(), p2], 1), torch.zeros(16, 2, dtype=F64)], 1)
        model = ExactResponse(SeatBaseExcitation(), 0.01, "spline", 4, initial_state="unknown")
        inputs = torch.randn(16, 116, 1, generator=g, dtype=F64)
        clean = model.outputs(truth, model.prepare(inputs, 8, 100), 8, 100)
        targets = clean + 0.05 * clean.std() * torch.randn(clean.shape, generator=g, dtype=F64)
        problem = LeastSquaresProblem(targets, inputs, 0.01, model=model, input_offset=8, observed=(True,))
        problems.append((problem, truth * torch.tensor([1.3, 0.7, 1.0, 1.0], dtype=F64)))
    return problems


def test_solves_on_two_threads_are_the_sequential_ones_bit_for_bit():
    problems = _seat_problems(3)

    def solve(item):
        problem, start = item
        return build_solver("gauss_newton", max_iterations=12).solve(problem, start)

    one, two = [solve(item) for item in problems], parallel_map(solve, problems, 2)
    for a, b in zip(one, two):
        assert torch.equal(a.params, b.params) and torch.equal(a.status, b.status)
        assert torch.equal(a.std, b.std) and torch.equal(a.loss, b.loss)


def test_the_cores_are_shared_among_a_distributed_runs_processes(monkeypatch):
    monkeypatch.setattr(_blas.os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    monkeypatch.delenv("LOCAL_WORLD_SIZE", raising=False)
    assert available_cores() == 8
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert available_cores() == 4
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "16")
    assert available_cores() == 1


def test_the_occupant_selection_is_the_same_on_one_thread_or_two(tmp_path):
    """occupant_roadfree's default on persons at 5 % noise (three models, the winner's delay variant, the weighing,
    the profile interval): every estimate, interval, evidence and status the same whatever occupant.workers."""
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.estimation.blocks import build_inputs
    from hybridqcm.estimation.plan import validate
    from hybridqcm.estimation.runner import build_module, build_refinement

    make_foreign(tmp_path / "p.h5", n=3, seed=21, occupant="body1", noise=0.05)
    records = []
    for workers in (1, 2):
        overrides = ["experiment=occupant_roadfree", f"data.path={tmp_path / 'p.h5'}", f"occupant.workers={workers}"]
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            cfg = compose("estimate", overrides)
        plan = validate(cfg)
        selection, module = build_refinement(cfg, plan), build_module(cfg, plan)
        assert selection.workers == workers
        records.append(selection.refine(module.prepare(build_inputs(cfg, plan))))
    one, two = records

    def same(a, b, what):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=what)

    for key in ("params", "m3_low", "m3_high"):
        same(one[key], two[key], key)
    same(one["final"].status, two["final"].status, "status")
    same(one["final"].std, two["final"].std, "std")
    for key, value in one["extra"].items():
        if torch.is_tensor(value):
            same(value, two["extra"][key], key)
        else:
            assert value == two["extra"][key], key
    assert any(torch.isfinite(one["extra"][f"logz_{n}+delay"]).any() for n in ("rigid", "body1", "body2"))


def test_a_stop_request_ends_the_solves_on_threads_promptly():
    """Ctrl-C while solves run on worker threads: the handler raises in the main thread, and the workers, which a
    signal never reaches, see the request at their next check (the solver's, every iteration): the map ends within
    a fraction of a second, not when the solves would have."""
    import os
    import signal

    from hybridqcm import interrupt

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    running = threading.Barrier(3)

    def endless(k):
        running.wait()
        while True:  # a long solve: the solver's iterations check for a stop
            interrupt.check_stop()
            time.sleep(0.005)

    interrupt.install()
    try:
        timer = threading.Timer(0.2, lambda: (running.wait(), os.kill(os.getpid(), signal.SIGINT)))
        timer.start()
        start = time.perf_counter()
        with pytest.raises(interrupt.Interrupted):
            parallel_map(endless, range(2), 2)
        assert time.perf_counter() - start < 5.0
        timer.join()
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)
        interrupt._pending = None


def test_the_solver_stops_at_a_pending_stop_request(monkeypatch):
    from hybridqcm import interrupt

    problem, start = _seat_problems(1)[0]
    monkeypatch.setattr(interrupt, "_pending", 2)  # SIGINT recorded (in another thread's handler)
    with pytest.raises(interrupt.Interrupted):
        build_solver("gauss_newton", max_iterations=5).solve(problem, start)


def test_even_slices_cover_the_rows_once_in_order_with_lengths_one_apart():
    from hybridqcm.estimation._blas import even_slices

    for n in (0, 1, 2, 5, 10, 17000, 17001):
        for parts in (1, 2, 3, 7):
            slices = even_slices(n, parts)
            assert [r for s in slices for r in range(s.start, s.stop)] == list(range(n))
            lengths = [s.stop - s.start for s in slices]
            assert len(slices) == min(parts, n) and all(length > 0 for length in lengths)
            assert lengths == sorted(lengths, reverse=True) and (not lengths or lengths[0] - lengths[-1] <= 1)
    assert [(s.start, s.stop) for s in even_slices(10, 3)] == [(0, 4), (4, 7), (7, 10)]
