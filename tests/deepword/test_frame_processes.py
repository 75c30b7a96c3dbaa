from deepword import frame_processes
from deepword.frame_processes import frame_processes as processes_for
from deepword.frame_processes import map_frames


def test_a_process_is_started_only_for_a_task_of_frames_or_more(monkeypatch):
    assert processes_for(2, 15) == 1 and processes_for(2, 16) == 2 and processes_for(4, 100) == 4
    assert processes_for(2, 3, frames_per_task=1) == 2 and processes_for(1, 100) == 1 and processes_for(2, 0) == 1
    monkeypatch.setattr(frame_processes, "FRAMES_PER_TASK", 1)   # read at call time: tests shrink it
    assert processes_for(2, 3) == 2


def test_the_results_come_in_the_frames_order_whatever_the_processes():
    frames = [-3, 5, -1, 0, 7, -2, 4]
    seen = []

    def progress(results, total):
        seen.append(total)
        yield from results

    one = map_frames(abs, frames, workers=1, progress=progress)
    two = map_frames(abs, frames, workers=2, progress=progress, frames_per_task=2)
    assert one == two == [abs(f) for f in frames] and seen == [7, 7]
    assert map_frames(abs, [], workers=2) == []
