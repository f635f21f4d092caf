"""The folder each strip writes into (addon.pipeline.folder_name): readable where the strip's
name allows, and never shared by two names, on any file system."""

import re

import pytest

from addon.pipeline import folder_name

# Names that all mapped to one folder before ('strip', 'a_b', 'shot'), names that differ only in
# case (one folder on Windows and macOS), names that look like another name's folder, names
# Windows reserves, names that are no folder at all.
NAMES = ["顔", "名前", "", "a/b", "a b", "a_b", "a__b", "a_b_", "_a_b", "a.b", "a..b", "Shot",
         "shot", "SHOT", "shot_0123abcd", "Shot_0123abcd", "con", "CON", "con.mov", "nul", "com1",
         "lpt9.exr", ".", "..", "...", "a.", ".a", "-a", "ä", "a\u0308", "strip", "x" * 63,
         "frame_0001.png", "clip.mov", "s01-e02_take3"]


def test_distinct_names_never_share_a_folder_even_where_case_is_ignored():
    folders = [folder_name(n) for n in NAMES]
    assert len({f.lower() for f in folders}) == len(NAMES), folders


@pytest.mark.parametrize("name", NAMES)
def test_every_folder_is_a_plain_ascii_name_any_file_system_takes(name):
    folder = folder_name(name)
    assert re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", folder), folder
    assert not folder.endswith(".") and folder.split(".")[0].lower() not in (
        "con", "prn", "aux", "nul", *(f"com{i}" for i in range(10)),
        *(f"lpt{i}" for i in range(10)))
    assert len(folder) <= len(name.encode()) + 9 + len("strip")
    assert folder_name(name) == folder  # the same name: the same folder, every run


def test_plain_names_stay_readable():
    for name in ("frame_0001.png", "clip.mov", "s01-e02_take3", "strip", "a_b"):
        assert folder_name(name) == name
    for name in ("a/b", "Shot", "顔", "con"):  # readable prefix, the hash tells them apart
        assert re.fullmatch(r".*_[0-9a-f]{8}", folder_name(name))
    assert folder_name("a/b").startswith("a_b_") and folder_name("Shot").startswith("Shot_")
    assert folder_name("顔").startswith("strip_") and folder_name("名前").startswith("strip_")
