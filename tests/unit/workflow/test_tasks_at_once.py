"""A task's memory peaks are its worker process's: :class:`TasksAtOnce` says how many tasks shared them."""
import threading

from mmflow.bench.cluster import TRACED_TOLERANCE, plan_vs_traced
from mmflow.workflow.engine.resources import TasksAtOnce


def test_tasks_that_overlap_count_each_other_and_one_alone_counts_itself():
    entered, release = threading.Barrier(2), threading.Event()
    seen = {}

    def task(name):
        with TasksAtOnce() as n:
            entered.wait()  # both inside
            release.wait()
        seen[name] = n.most

    threads = [threading.Thread(target=task, args=(k,)) for k in "ab"]
    for t in threads:
        t.start()
    release.set()
    for t in threads:
        t.join()
    with TasksAtOnce() as alone:
        pass
    # a task entering after another left does not raise the other's count, nor its own
    with TasksAtOnce() as first:
        pass
    with TasksAtOnce() as second:
        pass
    assert seen == {"a": 2, "b": 2} and alone.most == 1 and (first.most, second.most) == (1, 1)
    assert TasksAtOnce._running == []


def test_the_plan_is_compared_with_peaks_of_tasks_that_ran_alone(monkeypatch, tmp_path):
    """``plan_vs_traced`` reads only the tasks that recorded running alone; a stage whose tasks all shared their
    worker is reported with how many did and ``within: None``, as one whose tasks recorded no count."""
    import mmflow.workflow.engine.rundir as rundir
    import mmflow.workflow.plan.planner as planner

    infos = {"calibrate": {"k1": {"traced_peak_bytes": 100, "tasks_at_once": 1},
                           "k2": {"traced_peak_bytes": 190, "tasks_at_once": 2}},
             "mmodes": {"k1": {"traced_peak_bytes": 200, "tasks_at_once": 2}},
             "solve": {"k1": {"traced_peak_bytes": 50}}}  # a run from before the count: not known to be alone

    class Run:
        def __init__(self, path):
            pass

        def task_infos(self, stage):
            return infos.get(stage, {})

    monkeypatch.setattr(rundir, "RunDir", Run)
    monkeypatch.setattr(planner, "plan", lambda cfg, peak_gflops: {"stages": [
        {"stage": "calibrate", "task_bytes": 110}, {"stage": "mmodes", "task_bytes": 100},
        {"stage": "solve", "task_bytes": 50}]})
    out = plan_vs_traced(None, tmp_path, 100.0)
    assert out["calibrate"]["traced_gb"] == round(100 / 1e9, 4) and out["calibrate"]["tasks_alone"] == 1
    assert out["calibrate"]["within"] is (abs(110 / 100 - 1) <= TRACED_TOLERANCE)
    assert out["mmodes"]["within"] is None and out["mmodes"]["tasks_at_once"] == 2
    assert out["solve"]["within"] is None and out["solve"]["tasks_at_once"] is None
