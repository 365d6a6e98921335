"""cifilter.montecarlo: chunked, seeded Monte Carlo in process and on a real Dask cluster."""

import functools
import io
import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from cifilter import montecarlo
from cifilter._progress import ProgressBar


def gaussian_study(rng, runs, dim=2):
    """NEES of standard normal errors, plus a per-run vector (two keys, two shapes)."""
    errors = rng.standard_normal((runs, dim))
    return {"nees": np.sum(errors**2, axis=1), "errors": errors}


def failing_study(rng, runs, bad_runs=7):
    """Fails in exactly the chunk whose size is ``bad_runs`` (the last one below)."""
    if runs == bad_runs:
        raise FloatingPointError("simulated divergence")
    return {"x": rng.standard_normal(runs)}


def dying_study(rng, runs, bad_runs=7):
    """Kills the worker process that runs the chunk whose size is ``bad_runs``."""
    if runs == bad_runs:
        os._exit(3)
    return {"x": rng.standard_normal(runs)}


def expected_by_hand(seed, runs, chunk_size):
    """The documented seeding, written out: chunk k uses SeedSequence(seed).spawn(n)[k]."""
    n_chunks = -(-runs // chunk_size)
    children = np.random.SeedSequence(seed).spawn(n_chunks)
    parts = [gaussian_study(np.random.default_rng(children[k]),
                            min(chunk_size, runs - k * chunk_size)) for k in range(n_chunks)]
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


# --- in process ---------------------------------------------------------------------------

def test_in_process_follows_the_documented_seeding():
    result = montecarlo.run(gaussian_study, 250, chunk_size=100, seed=42, progress=False)
    expected = expected_by_hand(42, 250, 100)
    assert list(result) == ["nees", "errors"]
    assert result["errors"].shape == (250, 2)
    for key in expected:
        np.testing.assert_array_equal(result[key], expected[key])


def test_same_seed_same_numbers_other_seed_other_numbers():
    a = montecarlo.run(gaussian_study, 300, chunk_size=64, seed=3, progress=False)
    b = montecarlo.run(gaussian_study, 300, chunk_size=64, seed=3, progress=False)
    c = montecarlo.run(gaussian_study, 300, chunk_size=64, seed=4, progress=False)
    np.testing.assert_array_equal(a["nees"], b["nees"])
    assert not np.array_equal(a["nees"], c["nees"])


def test_default_chunk_size_is_the_documented_one():
    runs = 2 * montecarlo.DEFAULT_CHUNK_SIZE + 5
    default = montecarlo.run(gaussian_study, runs, seed=9, progress=False)
    explicit = expected_by_hand(9, runs, montecarlo.DEFAULT_CHUNK_SIZE)
    np.testing.assert_array_equal(default["nees"], explicit["nees"])


def test_seed_sequence_and_generator_seeds_are_reproducible():
    a = montecarlo.run(gaussian_study, 50, chunk_size=20, seed=np.random.SeedSequence(5),
                       progress=False)
    b = montecarlo.run(gaussian_study, 50, chunk_size=20, seed=5, progress=False)
    np.testing.assert_array_equal(a["nees"], b["nees"])
    g1 = montecarlo.run(gaussian_study, 50, chunk_size=20, seed=np.random.default_rng(1),
                        progress=False)
    g2 = montecarlo.run(gaussian_study, 50, chunk_size=20, seed=np.random.default_rng(1),
                        progress=False)
    np.testing.assert_array_equal(g1["nees"], g2["nees"])


def test_one_chunk_and_a_chunk_larger_than_the_study():
    result = montecarlo.run(gaussian_study, 7, chunk_size=1000, seed=1, progress=False)
    expected = gaussian_study(np.random.default_rng(np.random.SeedSequence(1).spawn(1)[0]), 7)
    np.testing.assert_array_equal(result["nees"], expected["nees"])


def test_failing_chunk_names_chunk_and_seed_and_keeps_finished_chunks():
    # 47 runs in chunks of 10: chunks 0-3 have 10 runs, chunk 4 has the 7 that fail.
    with pytest.raises(montecarlo.MonteCarloError) as caught:
        montecarlo.run(failing_study, 47, chunk_size=10, seed=11, progress=False)
    error = caught.value
    message = str(error)
    assert "chunk 4 of 5" in message and "runs 40..46" in message
    assert "spawn_key=(4,)" in message and f"entropy={11}" in message
    assert "FloatingPointError: simulated divergence" in message
    assert isinstance(error.__cause__, FloatingPointError)
    (failure,) = error.failed
    assert (failure.index, failure.start, failure.runs) == (4, 40, 7)
    assert failure.seed_sequence.spawn_key == (4,) and failure.seed_sequence.entropy == 11
    # Nothing finished is lost: the partial result equals the first 40 runs of a good study.
    assert sorted(error.completed) == [0, 1, 2, 3] and error.not_run == []
    children = np.random.SeedSequence(11).spawn(5)
    expected = np.concatenate([np.random.default_rng(children[k]).standard_normal(10)
                               for k in range(4)])
    np.testing.assert_array_equal(error.partial["x"], expected)
    np.testing.assert_array_equal(error.partial_runs, np.arange(40))


def test_failure_in_the_middle_stops_in_process_and_lists_what_did_not_run():
    study = functools.partial(failing_study, bad_runs=10)  # the first chunk of 10 fails
    with pytest.raises(montecarlo.MonteCarloError) as caught:
        montecarlo.run(study, 35, chunk_size=10, seed=0, progress=False)
    error = caught.value
    assert error.failed[0].index == 0 and error.completed == {}
    assert error.partial == {} and error.partial_runs.shape == (0,)
    assert error.not_run == [1, 2, 3]


def test_failed_chunk_can_be_rerun_alone_from_its_seed():
    with pytest.raises(montecarlo.MonteCarloError) as caught:
        montecarlo.run(failing_study, 47, chunk_size=10, seed=11, progress=False)
    failure = caught.value.failed[0]
    rerun = gaussian_study(np.random.default_rng(failure.seed_sequence), failure.runs)
    full = montecarlo.run(gaussian_study, 47, chunk_size=10, seed=11, progress=False)
    np.testing.assert_array_equal(rerun["nees"], full["nees"][failure.start:])


@pytest.mark.parametrize("study, problem", [
    (lambda rng, runs: [1.0] * runs, TypeError),
    (lambda rng, runs: {"x": np.zeros(runs + 1)}, ValueError),
    (lambda rng, runs: {"x": 1.0}, ValueError),
])
def test_bad_study_output_is_reported_as_a_chunk_failure(study, problem):
    with pytest.raises(montecarlo.MonteCarloError, match="chunk 0") as caught:
        montecarlo.run(study, 5, seed=0, progress=False)
    assert isinstance(caught.value.failed[0].error, problem)
    assert "study" in str(caught.value.failed[0].error)


@pytest.mark.parametrize("kwargs, problem, name", [
    ({"study": None}, TypeError, "study"),
    ({"runs": 0}, ValueError, "runs"),
    ({"runs": 2.5}, TypeError, "runs"),
    ({"runs": True}, TypeError, "runs"),
    ({"chunk_size": 0}, ValueError, "chunk_size"),
    ({"chunk_size": "10"}, TypeError, "chunk_size"),
    ({"seed": -1}, ValueError, "seed"),
    ({"seed": "1"}, TypeError, "seed"),
    ({"progress": "yes"}, TypeError, "progress"),
    ({"client": 3}, TypeError, "client"),
])
def test_bad_arguments_name_the_argument(kwargs, problem, name):
    arguments = {"study": gaussian_study, "runs": 10, "seed": 0, "progress": False} | kwargs
    study = arguments.pop("study")
    runs = arguments.pop("runs")
    with pytest.raises(problem, match=name):
        montecarlo.run(study, runs, **arguments)


@pytest.mark.parametrize("kwargs, problem", [
    ({"workers": 0}, ValueError),
    ({"workers": "2"}, TypeError),
    ({"scheduler": ""}, ValueError),
    ({"scheduler": 8786}, TypeError),
    ({"workers": 1, "scheduler": "tcp://localhost:8786"}, ValueError),
    ({"timeout": 0}, ValueError),
    ({"timeout": -1.0, "scheduler": "tcp://localhost:8786"}, ValueError),
    ({"timeout": float("nan")}, ValueError),
    ({"timeout": "5"}, TypeError),
    ({"timeout": True}, TypeError),
])
def test_dask_client_argument_errors(kwargs, problem):
    with pytest.raises(problem):
        with montecarlo.dask_client(**kwargs):
            pass


DASK_HINT = r'pip install "\.\[distributed\]" from a clone.*"cifilter-fusion\[distributed\]"'


def test_missing_dask_gives_an_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import now raises ImportError
    with pytest.raises(ImportError, match=DASK_HINT):
        montecarlo.run(gaussian_study, 10, client="tcp://127.0.0.1:1", progress=False)
    with pytest.raises(ImportError, match=DASK_HINT):
        with montecarlo.dask_client(workers=1):
            pass


# --- progress bar -------------------------------------------------------------------------

def test_progress_bar_on_request_goes_to_stderr(capsys):
    montecarlo.run(gaussian_study, 30, chunk_size=10, seed=0, progress=True)
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "gaussian_study" in captured.err
    assert "30/30 runs" in captured.err and "[####################]" in captured.err
    assert captured.err.endswith("\n")


def test_progress_false_and_automatic_off_a_terminal_are_silent(capsys):
    montecarlo.run(gaussian_study, 30, chunk_size=10, seed=0, progress=False)
    montecarlo.run(gaussian_study, 30, chunk_size=10, seed=0)  # stderr is not a terminal
    assert capsys.readouterr().err == ""


class FakeTerminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_bar_draws_counts_and_time_left():
    stream = FakeTerminal()
    with ProgressBar(4, label="study", unit="runs", enabled=True, stream=stream) as bar:
        bar.update(1)
        text_after_one = stream.getvalue()
        bar.update(3)
    assert "study  [#####---------------]  1/4 runs" in text_after_one
    assert "left" in text_after_one
    assert "4/4 runs" in stream.getvalue() and stream.getvalue().endswith("\n")


def test_automatic_progress_bar_waits_before_appearing():
    quick = FakeTerminal()
    with ProgressBar(4, enabled=None, stream=quick, delay=60.0) as bar:
        bar.update(4)
    assert quick.getvalue() == ""
    slow = FakeTerminal()
    with ProgressBar(4, enabled=None, stream=slow, delay=0.0) as bar:
        bar.update(4)
    assert "4/4 runs" in slow.getvalue()


# --- on a real Dask cluster ---------------------------------------------------------------

@pytest.fixture(scope="module")
def thread_clusters():
    """Two in-process LocalClusters (1 and 2 single-threaded workers): cheap to start."""
    distributed = pytest.importorskip("distributed")
    clients = {}
    for workers in (1, 2):
        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1,
                                           processes=False, dashboard_address=":0")
        clients[workers] = (cluster, distributed.Client(cluster, set_as_default=False))
    yield {workers: client for workers, (_, client) in clients.items()}
    for cluster, client in clients.values():
        client.close()
        cluster.close()


@pytest.mark.parametrize("workers", [1, 2])
def test_dask_gives_the_in_process_numbers(thread_clusters, workers):
    here = montecarlo.run(gaussian_study, 230, chunk_size=25, seed=7, progress=False)
    there = montecarlo.run(gaussian_study, 230, chunk_size=25, seed=7, progress=False,
                           client=thread_clusters[workers])
    for key in here:
        np.testing.assert_array_equal(there[key], here[key])


def test_dask_through_a_scheduler_address(thread_clusters):
    address = thread_clusters[2].scheduler.address
    here = montecarlo.run(gaussian_study, 60, chunk_size=25, seed=1, progress=False)
    there = montecarlo.run(gaussian_study, 60, chunk_size=25, seed=1, progress=False,
                           client=address)
    np.testing.assert_array_equal(there["nees"], here["nees"])


def test_dask_failing_chunk_keeps_every_finished_chunk(thread_clusters):
    with pytest.raises(montecarlo.MonteCarloError) as caught:
        montecarlo.run(failing_study, 47, chunk_size=10, seed=11, progress=False,
                       client=thread_clusters[2])
    error = caught.value
    assert "chunk 4 of 5" in str(error) and "spawn_key=(4,)" in str(error)
    assert isinstance(error.failed[0].error, FloatingPointError)
    # On Dask every submitted chunk runs to its end, so chunks 0-3 are all in .partial.
    assert sorted(error.completed) == [0, 1, 2, 3] and error.not_run == []
    children = np.random.SeedSequence(11).spawn(5)
    expected = np.concatenate([np.random.default_rng(children[k]).standard_normal(10)
                               for k in range(4)])
    np.testing.assert_array_equal(error.partial["x"], expected)


def test_local_process_cluster_from_workers_argument():
    """``dask_client(workers=2)``: the CLI's --workers, two real worker processes."""
    pytest.importorskip("distributed")
    cloudpickle = pytest.importorskip("cloudpickle")
    # The workers cannot import this test module: ship its functions by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        here = montecarlo.run(gaussian_study, 120, chunk_size=30, seed=5, progress=False)
        with montecarlo.dask_client(workers=2) as client:
            info = client.scheduler_info()
            assert len(info["workers"]) == 2
            assert all(w["nthreads"] == 1 for w in info["workers"].values())
            there = montecarlo.run(gaussian_study, 120, chunk_size=30, seed=5,
                                   progress=False, client=client)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    np.testing.assert_array_equal(there["nees"], here["nees"])
    np.testing.assert_array_equal(there["errors"], here["errors"])


def test_a_dying_worker_ends_in_monte_carlo_error_with_the_finished_chunks(monkeypatch):
    """The study kills its worker process (``os._exit``) in one chunk: Dask retries the
    chunk on a restarted worker until it gives up (``KilledWorker``; one retry allowed
    here instead of Dask's three, to keep the test short), and the study ends in
    MonteCarloError naming that chunk, with every other chunk finished and kept, bit for
    bit the in-process numbers."""
    pytest.importorskip("distributed")
    cloudpickle = pytest.importorskip("cloudpickle")
    import dask

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        # (worker-saturation 1.0: a worker holds only the chunk it runs, so its death is
        # charged to that chunk alone; with Dask's default a chunk queued behind the dying
        # one may be charged too and end in KilledWorker as well, seen 2 times in 8)
        with dask.config.set({"distributed.scheduler.allowed-failures": 1,
                              "distributed.scheduler.worker-saturation": 1.0}), \
                montecarlo.dask_client(workers=2) as client:
            with pytest.raises(montecarlo.MonteCarloError) as caught:
                montecarlo.run(dying_study, 47, chunk_size=10, seed=11, progress=False,
                               client=client)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    error = caught.value
    assert "chunk 4 of 5" in str(error) and "spawn_key=(4,)" in str(error)
    assert [failure.index for failure in error.failed] == [4]
    assert type(error.failed[0].error).__name__ == "KilledWorker"
    assert sorted(error.completed) == [0, 1, 2, 3] and error.not_run == []
    children = np.random.SeedSequence(11).spawn(5)
    expected = np.concatenate([np.random.default_rng(children[k]).standard_normal(10)
                               for k in range(4)])
    np.testing.assert_array_equal(error.partial["x"], expected)
    np.testing.assert_array_equal(error.partial_runs, np.arange(40))


@pytest.fixture
def silent_scheduler():
    """A TCP port that accepts connections and never sends a byte (a wedged scheduler, or
    another program on Dask's port): its address."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    held = []

    def accept():
        while True:
            try:
                connection, _ = server.accept()
            except OSError:
                return
            held.append(connection)

    threading.Thread(target=accept, daemon=True).start()
    yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
    server.close()
    for connection in held:
        connection.close()


def _within(seconds, call):
    """``call()`` in a thread: what it raised, or AssertionError if it is still running
    after ``seconds`` (it hung: the thread is left behind, a daemon)."""
    outcome = {}

    def target():
        try:
            call()
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    start = time.perf_counter()
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"still waiting after {seconds} s"
    return outcome.get("error"), time.perf_counter() - start


def test_a_scheduler_that_accepts_and_never_answers_is_given_up(silent_scheduler):
    """Issue 21, item 6: Dask's client waits for the scheduler's handshake without a
    timeout, so an address that accepts and stays silent made ``dask_client`` and
    ``run(client=address)`` wait forever."""
    pytest.importorskip("distributed")
    import dask

    def connect():
        with montecarlo.dask_client(scheduler=silent_scheduler, timeout=1.0):
            pass

    error, elapsed = _within(20, connect)
    assert isinstance(error, TimeoutError) and isinstance(error, OSError)
    assert silent_scheduler in str(error) and "did not answer within 1 s" in str(error)
    assert elapsed < 10

    def run():
        with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
            montecarlo.run(gaussian_study, 10, client=silent_scheduler, progress=False)

    error, elapsed = _within(20, run)
    assert isinstance(error, TimeoutError) and elapsed < 10


def test_the_command_line_gives_up_a_silent_scheduler_in_one_line(silent_scheduler):
    """``demo --scheduler`` at such an address: a one-line error and exit status 2 within
    the command line's scheduler timeout (5 s), instead of waiting forever."""
    pytest.importorskip("distributed")
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "cifilter", "demo", "--scheduler",
                           silent_scheduler, "--runs", "2", "--steps", "3"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("python -m cifilter demo: error: --scheduler: ")
    assert silent_scheduler in lines[0] and "did not answer within 5 s" in lines[0]
    assert time.perf_counter() - start < 30
