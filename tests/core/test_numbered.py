"""Relit frames under the footage's own numbers (addon/numbered.py): names, padding, hard links."""

import os

import pytest

from addon import frames, numbered, pipeline
from addon.errors import OutputError


@pytest.mark.parametrize("names,numbers,digits", [
    (["shot.1001.exr", "shot.1002.exr"], [1001, 1002], 4),
    (["plate_0998.png", "plate_0999.png", "plate_1000.png"], [998, 999, 1000], 4),
    (["a.00007.exr"], [7], 5),
    (["f1.png", "f2.png"], [1, 2], 1),
    (["portrait.png"], [12], numbered.MOVIE_DIGITS),  # unnumbered: counts from first_number
])
def test_sequence_numbering_keeps_numbers_and_padding(names, numbers, digits):
    assert numbered.sequence_numbering([f"/x/{n}" for n in names], 12) == (numbers, digits)
    assert numbered.numbered_name("relit", numbers[0], digits) == \
        f"relit.{numbers[0]:0{digits}d}.exr"


def test_negative_scene_frames_get_a_sign():
    assert numbered.numbered_name("relit", -3, 4) == "relit.-003.exr"


def fake_run(out, count, matte=False):
    """The pipeline's layout for ``count`` finished frames (contents tell them apart)."""
    for i in range(count):
        for path in [pipeline.relit_path(out, i)] + ([pipeline.matte_path(out, i)] if matte
                                                      else []):
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, "wb") as f:
                f.write(f"{os.path.basename(path)}".encode())


def test_published_frames_are_the_pipelines_files(tmp_path):
    fake_run(tmp_path, 3, matte=True)
    names = numbered.publish_frames(tmp_path, [0, 1, 2], [1001, 1002, 1003], 4, matte=True)
    assert names == ["relit.1001.exr", "relit.1002.exr", "relit.1003.exr"]
    for i, n in enumerate((1001, 1002, 1003)):
        assert os.path.samefile(tmp_path / f"relit.{n}.exr", pipeline.relit_path(tmp_path, i))
        assert os.path.samefile(tmp_path / f"matte.{n}.exr", pipeline.matte_path(tmp_path, i))
    assert not list(tmp_path.glob("*.partial"))


def test_a_chunk_publishes_only_its_frames_and_a_rerun_relinks_a_replaced_frame(tmp_path):
    fake_run(tmp_path, 4)
    numbered.publish_frames(tmp_path, [2, 3], [10, 11, 12, 13], 4)
    assert sorted(p.name for p in tmp_path.glob("relit.*.exr")) == ["relit.0012.exr",
                                                                    "relit.0013.exr"]
    # An overwrite run renames a new file into place: the published name follows it.
    new = pipeline.relit_path(tmp_path, 2)
    os.replace(new, new + ".old")
    with open(new, "wb") as f:
        f.write(b"new")
    numbered.publish_frames(tmp_path, [2], [10, 11, 12, 13], 4)
    assert (tmp_path / "relit.0012.exr").read_bytes() == b"new"


def test_copies_where_there_are_no_hard_links(tmp_path, monkeypatch):
    fake_run(tmp_path, 1)

    def no_links(src, dst):
        raise OSError(1, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_links)
    numbered.publish_frames(tmp_path, [0], [5], 4)
    published = tmp_path / "relit.0005.exr"
    assert published.read_bytes() == b"relit_000000.exr"
    assert not os.path.samefile(published, pipeline.relit_path(tmp_path, 0))


def test_an_unfinished_frame_is_an_error_and_stale_partials_are_swept(tmp_path):
    fake_run(tmp_path, 1)
    stale = tmp_path / "relit.0001.exr.somehost_999999_1.partial"
    stale.write_bytes(b"")
    leftover = tmp_path / f"relit.0001.exr.{frames.HOST}_999999_1.partial"  # a dead writer's
    leftover.write_bytes(b"")
    with pytest.raises(OutputError, match="relit_000001.exr is missing"):
        numbered.publish_frames(tmp_path, [0, 1], [1, 2], 4)
    assert not leftover.exists()
    assert stale.exists()  # another machine's: it may still be writing
