"""The baseline cache of ``social eval``: hit, miss, invalidation by source and geometry."""

import os
import shutil

import pytest

from splatsearch.social.convoi.scenarios import make_scenario
from splatsearch.social.olivia import baseline_cache as bc


@pytest.fixture
def sources(tmp_path):
    d = tmp_path / "src"
    shutil.copytree(bc._CONVOI_DIR, d, ignore=shutil.ignore_patterns("__pycache__"))
    return str(d)


def test_hit_miss_and_invalidation(tmp_path, sources):
    cache = bc.BaselineCache(str(tmp_path / "cache"), source_dir=sources)
    calls = []

    def run(tag):
        def f():
            calls.append(tag)
            return {"robot": [tag]}
        return f

    scn = make_scenario("doorway", 500)
    assert cache.get(scn, "dwa", run("a")) == {"robot": ["a"]}
    assert (cache.hits, cache.misses) == (0, 1)
    # same scene, kind and sources: read back, not run
    assert bc.BaselineCache(cache.directory, source_dir=sources).get(make_scenario("doorway", 500), "dwa", run("b")) \
        == {"robot": ["a"]}
    assert calls == ["a"]
    # another kind, seed or geometry is another entry
    cache.get(scn, "human", run("c"))
    cache.get(make_scenario("doorway", 501), "dwa", run("d"))
    cache.get(make_scenario("doorway", 500, door_width=1.4), "dwa", run("e"))
    assert calls == ["a", "c", "d", "e"]
    # an edit of the baseline sources invalidates every entry
    with open(os.path.join(sources, "dwa.py"), "a", encoding="utf-8") as f:
        f.write("\n# edited\n")
    again = bc.BaselineCache(cache.directory, source_dir=sources)
    assert again.get(scn, "dwa", run("f")) == {"robot": ["f"]}
    assert (again.hits, again.misses) == (0, 1)


def test_corrupt_entry_is_a_miss(tmp_path, sources):
    cache = bc.BaselineCache(str(tmp_path / "c"), source_dir=sources)
    scn = make_scenario("hallway", 1000)
    cache.get(scn, "dwa", lambda: 1)
    with open(cache.path(scn, "dwa"), "wb") as f:
        f.write(b"not a pickle")
    assert cache.get(scn, "dwa", lambda: 2) == 2
    assert cache.get(scn, "dwa", lambda: 3) == 2


def test_rejects_a_file_as_directory(tmp_path):
    p = tmp_path / "f"
    p.write_text("x")
    with pytest.raises(NotADirectoryError):
        bc.BaselineCache(str(p))


def test_default_digest_covers_convoi_sources():
    d = bc.source_digest()
    assert len(d) == 64 and d == bc.source_digest()


def test_eval_cli_refuses_a_file_as_cache(tmp_path):
    import argparse

    from splatsearch.social.olivia.cli import register_olivia

    f = tmp_path / "file"
    f.write_text("x")
    parser = argparse.ArgumentParser()
    register_olivia(parser.add_subparsers(dest="cmd"))
    a = parser.parse_args(["eval", "--checkpoint", str(tmp_path / "none.npz"), "--baseline-cache", str(f)])
    assert a.func(a) == 2
