"""The documentation is code: every command on a page runs here, and the site builds strictly.

Each ```bash or ```python block in README.md and docs/*.md carries a marker, an HTML comment on
the line just above its fence (invisible on the rendered page):

- ``<!-- run: fast -->``: runs in the default tier; ``<!-- run: slow -->``: runs with ``-m slow``.
  Options: ``rc=N`` (the exit status the page promises; default 0), ``timeout=S``.
- ``<!-- run: by tests/FILE.py::TEST -->``: that test runs the block (it must exist).
- ``<!-- run: never -- REASON -->``: not run (installs packages, needs a cluster); kept few.

The blocks of a page run in order, as a reader would type them, in one fresh folder that looks
like the repository root (``configs/``, ``docs/``, ``benchmarks/``, ``scripts/``, the sample
recording, and ``../shared`` beside it). The default tier runs a page's fast blocks only (they
never need a slow one); ``-m slow`` runs all of them.

A ```text block marked ``<!-- output: rel=R abs=A ignore=REGEX -->`` is what the run block
before it prints (stdout and stderr together). Its lines, apart from ``…`` lines, must appear
in the output in that order. The words of each line must be the same; its numbers must agree
within ``abs + rel·|number|`` (defaults: exact), because simulated skies and the real pair's
matching move in the last digits from one build to the next. ``ignore`` (repeatable) blanks
what is not the program's result (a latency; with a group, only the group: one column of a
table, such as a layer's spread); ``<NAME>`` in a promised line stands for one word (a time
stamp in a file name).
"""
from __future__ import annotations

import contextlib
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from .conftest import REPO, SHARED

DOCS = REPO / "docs"
PAGES = ["README.md", *sorted(p.relative_to(REPO).as_posix() for p in DOCS.glob("*.md"))]
MARKER = re.compile(r"^<!--\s*(run|output):\s*(.*?)\s*-->\s*$")
FENCE = re.compile(r"^(\s*)```(\w*)")
COMMAND_LANGS = {"bash", "sh", "shell", "console", "python", "py"}


@dataclass
class Block:
    page: str
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    kind: str | None = None  # "run" | "output" | None
    args: str = ""
    output: "Block | None" = None  # the ```text block showing what this run block prints
    opts: dict = field(default_factory=dict)

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"

    @property
    def tier(self) -> str:
        return self.args.split()[0] if self.args else ""


def parse_blocks(page: str) -> list[Block]:
    """Every fenced block of a page, with the marker on the line above it (if any)."""
    lines = (REPO / page).read_text().splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, lang = m.group(1), m.group(2)
        j = i + 1
        while j < len(lines) and not lines[j].startswith(indent + "```"):
            j += 1
        code = "\n".join(ln[len(indent):] for ln in lines[i + 1:j]) + "\n"
        mk = MARKER.match(lines[i - 1].strip()) if i > 0 else None
        b = Block(page, i + 1, lang, code, mk.group(1) if mk else None, mk.group(2) if mk else "")
        if b.kind == "output" and blocks and blocks[-1].kind == "run":
            blocks[-1].output = b
        blocks.append(b)
        i = j + 1
    return blocks


def options(args: str) -> dict:
    """``key=value`` words of a marker (values may be quoted); ``ignore`` collects a list."""
    out: dict = {"ignore": []}
    for word in shlex.split(args):
        if "=" in word:
            k, v = word.split("=", 1)
            if k == "ignore":
                out["ignore"].append(v)
            else:
                out[k] = v
    return out


ALL_BLOCKS = {page: parse_blocks(page) for page in PAGES}


def run_blocks(page: str, tiers: tuple[str, ...]) -> list[Block]:
    return [b for b in ALL_BLOCKS[page] if b.kind == "run" and b.tier in tiers]


# --- what the pages promise, checked without running anything ------------------------------

def test_every_command_block_has_a_marker():
    missing = [b.where for bs in ALL_BLOCKS.values() for b in bs
               if b.lang in COMMAND_LANGS and b.kind != "run"]
    assert not missing, f"command blocks without a <!-- run: … --> marker: {missing}"
    bad = [b.where for bs in ALL_BLOCKS.values() for b in bs
           if b.kind == "run" and b.tier not in ("fast", "slow", "by", "never")]
    assert not bad, f"unknown run tier at {bad}"
    orphans = [b.where for bs in ALL_BLOCKS.values() for b in bs if b.kind == "output"
               and not any(r.output is b for r in bs)]
    assert not orphans, f"output blocks that follow no run block: {orphans}"


def test_blocks_run_elsewhere_name_a_test_that_exists():
    for b in (b for bs in ALL_BLOCKS.values() for b in bs if b.tier == "by"):
        path, name = b.args.split()[1].split("::")
        assert re.search(rf"^def {name}\(", (REPO / path).read_text(), re.M), b.where


def test_few_blocks_are_never_run():
    never = [b for bs in ALL_BLOCKS.values() for b in bs if b.tier == "never"]
    assert all("--" in b.args for b in never), "a block that never runs must say why"
    assert len(never) <= 6, [b.where for b in never]


def test_readme_is_a_short_front_door():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    # the two set-up commands come first, under "Quick start", byte for byte as they have always been
    quick = text.index("## Quick start")
    assert quick < text.index("python3.11 -m pip install") and text.count("\n## ", 0, quick) == 0
    cmds = [b.code.strip() for b in ALL_BLOCKS["README.md"] if b.lang == "bash"][:2]
    assert cmds == [
        "python3.11 -m pip install torch==2.13.0 -e . && cbh run --record",
        "python3.11 -m pip install torch==2.13.0 -e '.[test]' && python3.11 -m pytest",
    ]
    assert "docs/wahrsis-height-map.jpg" in text and "mkdocs serve" in text and "mkdocs build" in text


def test_readme_lists_every_command():
    out = subprocess.run([sys.executable, "-m", "cbh.cli.main", "--help"], capture_output=True,
                         text=True, check=True, env={**os.environ, "COLUMNS": "200"}).stdout
    commands = re.findall(r"^\s{2}(\w[\w-]*)\s{2,}", out.split("Commands:")[1], re.M)
    assert len(commands) >= 12
    table = (REPO / "README.md").read_text()
    missing = [c for c in commands if f"| `cbh {c}` |" not in table]
    assert not missing, f"commands missing from the README's table: {missing}"


def test_the_test_extra_installs_the_docs_tools():
    import tomllib

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(extras["docs"]) <= set(extras["test"]) or "cbh[docs]" in extras["test"]


def test_library_example_is_the_same_in_readme_and_docs():
    def example(page):
        return [b.code for b in ALL_BLOCKS[page] if b.lang == "python" and b.tier == "by"][0]

    assert example("README.md") == example("docs/index.md")


def test_accuracy_page_gives_the_randomized_skies_with_their_command():
    """The randomized-sky numbers name the command that made them, and the benchmark's own
    argument parser takes it (200 skies, two jobs)."""
    import importlib.util
    import shlex

    text = (DOCS / "accuracy.md").read_text()
    sec = text[text.index("## Randomized skies (benchmarks/eval_random.py)"):]
    cmd = re.search(r"`python (benchmarks/eval_random.py [^`]+)`", sec).group(1)
    assert "| layers found |" in sec
    spec = importlib.util.spec_from_file_location("eval_random", REPO / "benchmarks" / "eval_random.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    args = mod.parser().parse_args(shlex.split(cmd)[1:])
    assert (args.n, args.jobs) == (200, 2)


# --- comparing promised output with what a command printed ----------------------------------

NUMBER = re.compile(r"(?<![\w.])[-+−]?\d+(?:\.\d+)?(?![\w.])")
WORD = re.compile(r"<[A-Za-z_]+>")


def _skeleton(line: str) -> tuple[str, list[float]]:
    nums = [float(n.replace("−", "-")) for n in NUMBER.findall(line)]
    return " ".join(NUMBER.sub("#", line).split()), nums


def _line_regex(skeleton: str) -> re.Pattern:
    parts = [r"\S+" if WORD.fullmatch(p) else re.escape(p) for p in re.split(r"(<[A-Za-z_]+>)", skeleton)]
    return re.compile("".join(parts) + r"\Z")


def compare_output(promised: str, actual: str, opts: dict) -> list[str]:
    """Problems (empty: the output keeps the page's promise)."""
    rel, abs_ = float(opts.get("rel", 0)), float(opts.get("abs", 0))

    def blank(m):  # the whole match, or only its first group (one column of a table)
        if m.re.groups == 0:
            return "<?>"
        return m.group(0)[:m.start(1) - m.start(0)] + "<?>" + m.group(0)[m.end(1) - m.start(0):]

    def clean(text):
        for pat in opts["ignore"]:
            text = re.sub(pat, blank, text, flags=re.M)
        return [ln for ln in text.splitlines() if ln.strip()]

    want = [ln for ln in clean(promised) if ln.strip() not in ("…", "...")]
    got = [_skeleton(ln) for ln in clean(actual)]
    anywhere = opts.get("order") == "any"  # lines printed as work finishes, in any order
    problems, k, used = [], 0, set()
    for line in want:
        sk, nums = _skeleton(line)
        rx = _line_regex(sk)
        near = None
        for j in range(0 if anywhere else k, len(got)):
            if j in used or not (rx.match(got[j][0]) and len(got[j][1]) == len(nums)):
                continue
            if all(abs(g - p) <= abs_ + rel * abs(p) for g, p in zip(got[j][1], nums)):
                k = j + 1
                used.add(j)
                break
            near = near or got[j]
        else:
            problems.append(f"promised {line!r}" + (f"; nearest numbers {near[1]}" if near else "; no such line"))
    return problems


def test_output_comparison_is_numeric_and_two_sided():
    opts = {"rel": "0.01", "abs": "0", "ignore": [r"latency [\d.]+ s"]}
    assert not compare_output("layers 1204 m, 3486 m\n…\n", "x\nlayers 1210 m, 3470 m\n", opts)
    assert compare_output("layers 1204 m, 3486 m\n", "layers 1204 m, 3600 m\n", opts)   # a number off
    assert compare_output("layers 1204 m\n", "layers 1204 km\n", opts)                  # a word off
    assert not compare_output("latency 4.03 s | ok\n", "latency 0.39 s | ok\n", opts)
    col = {**opts, "ignore": [r"^\s*\d+\s+\d+\s+(\d+)"]}                                  # a column blanked
    assert not compare_output("  1  1204  12  0.5\n", "  1  1204  60  0.5\n", col)
    assert compare_output("  1  1204  12  0.5\n", "  1  1300  12  0.5\n", col)
    assert not compare_output("recorded: r/a-<UTC>.mcap\n", "recorded: r/a-20261202T1620Z.mcap\n", opts)
    assert compare_output("a 1\nb 2\n", "b 2\na 1\n", opts)                               # order kept
    assert not compare_output("a 1\nb 2\n", "b 2\na 1\n", {**opts, "order": "any"})
    assert compare_output("a 1\na 1\n", "a 1\n", {**opts, "order": "any"})                # each line once


# --- running the pages' examples -------------------------------------------------------------

def _workdir(tmp_path: Path) -> Path:
    """A fresh folder that looks like the repository root, with ../shared beside it."""
    work = tmp_path / "repo"
    work.mkdir()
    for name in ("configs", "docs", "benchmarks", "scripts"):
        (work / name).symlink_to(REPO / name)
    (work / "recordings").mkdir()
    for f in (REPO / "recordings").glob("sample-*"):
        (work / "recordings" / f.name).symlink_to(f)
    if SHARED.is_dir():
        (tmp_path / "shared").symlink_to(SHARED)
    return work


def _env(work: Path) -> dict:
    bindir = str(Path(sys.executable).parent)  # where this interpreter's `cbh`, `python`, `mkdocs` are
    return {**os.environ, "PATH": bindir + os.pathsep + os.environ.get("PATH", ""), "COLUMNS": "120",
            "NO_MKDOCS_2_WARNING": "1", "PYTHONWARNINGS": "ignore"}


def run_page(page: str, tiers: tuple[str, ...], tmp_path: Path) -> None:
    blocks = run_blocks(page, tiers)
    if any("../shared" in b.code for b in blocks) and not SHARED.is_dir():
        pytest.skip("../shared data not present beside the repository")
    work = _workdir(tmp_path)
    env = _env(work)
    for b in blocks:
        opts = options(b.args)
        if b.lang in ("python", "py"):
            script = tmp_path / f"block_{b.line}.py"
            script.write_text(b.code)
            argv = [sys.executable, str(script)]
        else:
            argv = ["bash", "-e", "-o", "pipefail", "-c", b.code]
        t0 = time.monotonic()
        # its own process group, so that what a block starts in the background (`… &`) ends with it
        proc = subprocess.Popen(argv, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, start_new_session=True)
        try:
            out, _ = proc.communicate(timeout=float(opts.get("timeout", 900)))
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
        took = time.monotonic() - t0
        want_rc = {int(rc) for rc in str(opts.get("rc", 0)).split("|")}
        assert proc.returncode in want_rc, (f"{b.where}: exit {proc.returncode} (page promises {opts.get('rc', 0)}) "
                                            f"after {took:.1f} s\n{b.code}\n--- output ---\n{out[-4000:]}")
        if b.output is not None:
            problems = compare_output(b.output.code, out, options(b.output.args))
            assert not problems, (f"{b.where}: output differs from {b.output.where}:\n  "
                                  + "\n  ".join(problems) + f"\n--- output ---\n{out[-4000:]}")


FAST_PAGES = [p for p in PAGES if run_blocks(p, ("fast",))]
SLOW_PAGES = [p for p in PAGES if run_blocks(p, ("slow",))]


@pytest.mark.parametrize("page", FAST_PAGES)
def test_fast_examples_run(page, tmp_path):
    run_page(page, ("fast",), tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("page", SLOW_PAGES)
def test_all_examples_run(page, tmp_path):
    run_page(page, ("fast", "slow"), tmp_path)


def test_mkdocs_build_strict(tmp_path):
    """The site builds with every warning an error (broken links, griffe's docstring warnings)."""
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f",
                        str(REPO / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                       cwd=tmp_path, env=_env(tmp_path), capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    site = tmp_path / "site"
    assert (site / "index.html").is_file()
    for page in ("station", "unattended", "outputs", "accuracy", "how-it-works", "conventions", "api/pipeline"):
        assert (site / page / "index.html").is_file(), page
    # the API pages are generated from the docstrings, not empty shells
    assert (site / "api" / "triangulate" / "index.html").read_text().count('id="cbh.geometry.triangulate.') >= 3
