"""The documentation a newcomer meets: a short README for users and maintainers whose figures are
the measured ones, and a repository that speaks of the product, not of how its work was organised
(history belongs to git log and the model cards' lineage)."""

import json
import pathlib
import re
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
TEXT_SUFFIXES = {".py", ".md", ".json", ".toml", ".txt", ".sh", ".js", ".cfg", ".ini", ".yml",
                 ".yaml", ""}

# Phrases about the work process: numbered sessions, issue numbers, closing notes.
PROCESS_WORDS = re.compile(
    r"\bsessions?[ -]\d|\b(this|last|previous|next|earlier|later) session\b"
    r"|\bissue ?#?\d|\bissue's\b|\bclosing notes?\b",
    re.IGNORECASE)


def tracked_text_files():
    try:
        out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split("\n")
        files = [ROOT / f for f in out if f]
    except (OSError, subprocess.CalledProcessError):  # not a git checkout: every file
        files = [p for p in ROOT.rglob("*") if p.is_file() and ".venv" not in p.parts]
    return [p for p in files if p.suffix in TEXT_SUFFIXES and p.is_file()]


def test_no_words_about_how_the_work_was_organised():
    offenders = []
    for path in tracked_text_files():
        if path == pathlib.Path(__file__).resolve():
            continue  # this guard's own examples
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if PROCESS_WORDS.search(line):
                offenders.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert offenders == [], "\n".join(offenders)


def test_the_guard_catches_process_words():
    for bad in ("trained in session 5", "the session-3 run", "issue 4's targets",
                "see the closing note", "as this session measured", "Issue #12"):
        assert PROCESS_WORDS.search(bad), bad
    for fine in ("onnxruntime.InferenceSession(path)", "the session fixture", "one session per "
                 "model", "sessions = {}", "a new session (", "the engine session."):
        assert not PROCESS_WORDS.search(fine), fine


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 200, len(lines)


def presets_table():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Presets", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 6 and re.fullmatch(r"\d[\d.]*", cells[2]):
            rows[cells[0]] = [float(c) for c in cells[2:]]
    return rows


def test_readme_presets_table_holds_the_measured_figures():
    rows = presets_table()
    assert set(rows) == {"Portrait (the default)", "Draft", "Standard", "Final", "(output = input)"}
    yale = json.loads((ROOT / "bench" / "results" / "yale.json").read_text())
    si = yale["results"]["scale_invariant"]
    balance = yale["balance_correlation"]
    for label, (psnr, lr, tb, level) in rows.items():
        if label.startswith("("):
            name, card_key = "identity", "identity"
            card = json.loads((ROOT / "models" / "relight-final.json").read_text())
        else:
            name, card_key = f"relight-{label.split()[0].lower()}", "model"
            card = json.loads((ROOT / "models" / f"{name}.json").read_text())
        assert psnr == pytest.approx(si[name]["all"]["psnr"], abs=0.006), label
        assert lr == pytest.approx(balance[name]["left_right"], abs=0.0006), label
        assert tb == pytest.approx(balance[name]["top_bottom"], abs=0.0006), label
        assert level == pytest.approx(card["metrics"][card_key]["rmse_level_fit"], abs=6e-5), label


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    paths = set(re.findall(r"`((?:bench|models|tests|farm|training|demo|addon|tools|scripts)/"
                           r"[\w./-]+?\.(?:md|py|js|png|json))`", text))
    paths |= set(re.findall(r"\]\(([\w./-]+\.png)\)", text))
    assert paths
    missing = [p for p in paths if "*" not in p and not (ROOT / p).exists()]
    assert missing == []
