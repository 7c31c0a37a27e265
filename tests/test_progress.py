"""Progress output: plain periodic lines when the stream is not a terminal (CI logs, files)."""
import io

from activetouch.experiments.progress import Progress, progress


def test_progress_to_a_file_prints_plain_lines_not_carriage_returns():
    buf = io.StringIO()
    bar = progress(5, "rumi on mug-0", stream=buf, every_s=0.0)
    assert isinstance(bar, Progress)
    for i in range(5):
        bar.set_postfix(nll=f"{10 - i:.1f}")
        bar.update(1)
    bar.close()
    text = buf.getvalue()
    assert "\r" not in text
    lines = text.strip().splitlines()
    assert len(lines) == 5
    assert lines[-1].startswith("rumi on mug-0: 5/5 steps (100 %)") and lines[-1].endswith("nll=6.0")


def test_progress_lines_are_rate_limited_but_the_last_always_prints():
    buf = io.StringIO()
    bar = Progress(100, "episodes", unit="episode", every_s=3600.0, stream=buf)
    for _ in range(100):
        bar.update(1)
    lines = buf.getvalue().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("episodes: 100/100 episodes")
