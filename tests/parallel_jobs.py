"""Jobs for tests/test_parallel.py, in a module of their own so that a worker process unpickling
them imports nothing heavy (the test module itself imports the whole evaluation stack)."""

import os


def square(x):
    return x * x


def die_once(marker):
    """Kill this worker process the first time (no exception, no cleanup), succeed when rerun."""
    if not os.path.exists(marker):
        open(marker, "w").close()
        os._exit(3)
    return "second try"


def die_always():
    os.kill(os.getpid(), 9)


def boom(marker):
    with open(marker, "a") as f:
        f.write("x")
    raise RuntimeError("boom")


def failing_warmup():
    raise OSError("no GPU here")
