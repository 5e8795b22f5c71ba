"""The documentation: README.md and docs/ (the site `./run docs` builds; the build itself is a
step of `./run test`).

- every relative link and image resolves to a file inside the repository, and every
  ``#anchor`` to a heading of its page;
- nothing in README.md, docs/ or mfp_mapper/ points outside the repository (``../shared``,
  ``MODEL.md``);
- what a user copies from the pages is right where the machine allows: the commands of README's
  "Map a recording" run through the installed ``mfp-mapper`` from another directory; every
  ``mfp-mapper`` command parses; the launch arguments, ``-p`` parameters and parameter-file
  keys exist; the workspace's colcon command finds both packages; the Python examples run;
- the hand-written tables that mirror code (launch arguments, drop reasons) list what the code
  has.
"""

from __future__ import annotations

import ast
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from mfp_mapper.cli import build_parser, main
from mfp_mapper.config.schema import SETTINGS

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SKIP_DIRS = {"build", "install", "log", "_generated", "node_modules", "example_output", "out"}

FENCE = re.compile(r"^(```+|~~~+)(.*)$")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
EXTERNAL = ("http://", "https://", "mailto:", "ftp://")


def markdown_files() -> list[Path]:
    """Every Markdown file of the repository (not build outputs, hidden or generated ones)."""
    found = []
    for path in sorted(ROOT.rglob("*.md")):
        parts = path.relative_to(ROOT).parts
        if any(p.startswith(".") or p in SKIP_DIRS for p in parts[:-1]):
            continue
        found.append(path)
    return found


def pages() -> list[Path]:
    """README.md and the site's pages."""
    return [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]


def blocks_and_prose(text: str) -> Iterator[tuple[str | None, str]]:
    """``(language, line)`` for the lines of fenced code blocks, ``(None, line)`` for the
    others (fence lines themselves are left out)."""
    fence = language = None
    for line in text.splitlines():
        stripped = line.strip()
        if fence is None:
            m = FENCE.match(stripped)
            if m:
                fence, language = m.group(1), m.group(2).strip()
            else:
                yield None, line
        elif stripped == fence:
            fence = None
            yield language, "\0end"  # marks the end of a block
        else:
            yield language, line


def prose_lines(text: str, keep_code_spans: bool = False) -> Iterator[str]:
    """The lines outside fenced code blocks, inline code spans removed unless asked to keep."""
    for language, line in blocks_and_prose(text):
        if language is None:
            yield line if keep_code_spans else re.sub(r"`[^`]*`", "", line)


def code_blocks(text: str, languages: tuple[str, ...]) -> Iterator[str]:
    """The contents of the fenced code blocks in these languages."""
    block: list[str] = []
    for language, line in blocks_and_prose(text):
        if language is None or language not in languages:
            continue
        if line == "\0end":
            yield "\n".join(block)
            block = []
        else:
            block.append(line)


def slug(title: str) -> str:
    """A heading's anchor as MyST (``myst_heading_anchors``) and GitHub make it."""
    title = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", title)  # a link's text
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The heading anchors of a Markdown page."""
    return {
        slug(m.group(2))
        for line in prose_lines(path.read_text(encoding="utf-8"), keep_code_spans=True)
        if (m := HEADING.match(line))
    }


def links(path: Path) -> Iterator[str]:
    for line in prose_lines(path.read_text(encoding="utf-8")):
        yield from LINK.findall(line)


def shell_commands(text: str) -> Iterator[list[str]]:
    """The commands of the page's bash blocks: continuation lines joined, comments dropped,
    ``&&`` chains split."""
    for block in code_blocks(text, ("bash", "sh", "shell", "console")):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            command: list[str] = []
            for word in [*words, "&&"]:
                if word in ("&&", ";", "||"):
                    if command:
                        yield command
                    command = []
                else:
                    command.append(word)


def all_commands() -> Iterator[tuple[Path, list[str]]]:
    for page in pages():
        for command in shell_commands(page.read_text(encoding="utf-8")):
            yield page, command


# --- links ------------------------------------------------------------------------------------


def test_readme_is_a_front_door() -> None:
    """About 200 lines, and the two commands that set up a fresh machine."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 220
    quick_start = list(shell_commands(readme_section("Quick start")))
    assert ["./run", "demo"] in quick_start and ["./run", "test"] in quick_start


def test_the_pages_are_found() -> None:
    names = {p.name for p in pages()}
    assert {"README.md", "index.md", "installation.md", "robot.md", "node.md", "cli.md"} <= names
    assert (DOCS / "conf.py").is_file()


@pytest.mark.parametrize("page", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_and_images_resolve_inside_the_repository(page: Path) -> None:
    bad = []
    for target in links(page):
        if target.startswith(EXTERNAL):
            continue
        file_part, _, anchor = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        if not dest.is_relative_to(ROOT):
            bad.append(f"{target}: outside the repository")
        elif not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target}: no heading '{anchor}' in {dest.relative_to(ROOT)}")
    assert not bad, f"{page.relative_to(ROOT)}: " + "; ".join(bad)


def test_the_link_checker_finds_what_it_must() -> None:
    text = '[a](x.md) ![b](img/p.png "t") `[c](no.md)` [d](https://e.org#x) [e](<f.md>)\n'
    text += "```bash\n[h](in_code.md)\n```\n## The core's `API` (v2)\n"
    found = [t for line in prose_lines(text) for t in LINK.findall(line)]
    assert found == ["x.md", "img/p.png", "https://e.org#x", "f.md"]
    assert slug("The core's `API` (v2)") == "the-cores-api-v2"
    assert slug("Migrating from octomap_server") == "migrating-from-octomap_server"


def test_nothing_points_outside_the_repository() -> None:
    files = [ROOT / "README.md"]
    files += [p for p in DOCS.rglob("*") if p.is_file() and "_generated" not in p.parts]
    files += list((ROOT / "mfp_mapper").rglob("*.py"))
    bad = []
    for path in files:
        if path.suffix in (".png", ".jpg", ".svg"):
            continue
        text = path.read_text(encoding="utf-8")
        for needle in ("../shared", "MODEL.md"):
            if needle in text:
                bad.append(f"{path.relative_to(ROOT)} names {needle}")
    assert not bad, "\n".join(bad)


# --- what a user copies -----------------------------------------------------------------------


def readme_section(title: str) -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end >= 0 else len(text)]


def launcher() -> Path:
    """``mfp-mapper`` as `source .venv/bin/activate` puts it on PATH."""
    path = ROOT / ".venv" / "bin" / "mfp-mapper"
    if not path.is_file():
        pytest.skip(f"{path} is made by ./run setup; not there")
    return path


def test_readme_commands_map_a_recording_from_another_directory(tmp_path: Path) -> None:
    """README's "Map a recording", as typed, in a directory outside the repository."""
    commands = list(shell_commands(readme_section("Map a recording")))
    assert [c[:2] for c in commands] == [
        ["mfp-mapper", "replay"],
        ["mfp-mapper", "render"],
        ["mfp-mapper", "query"],
    ]
    recording = commands[0][2].rstrip("/")
    argv = ["simulate", str(tmp_path / recording), "--scene", "small", "--scans", "12"]
    assert main([*argv, "--azimuths", "360"]) == 0
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # this checkout's code
    outputs = []
    for command in commands:  # (`mfp-mapper --help` anywhere: test_imports.py)
        proc = subprocess.run(
            [str(launcher()), *command[1:]],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert proc.returncode == 0, f"{shlex.join(command)}:\n{proc.stderr[-3000:]}"
        outputs.append(proc.stdout)
    assert (tmp_path / "map.npz").is_file()
    assert (tmp_path / "pictures" / "doo_topdown.png").is_file()
    assert "DoO" in outputs[-1] and "mean free path" in outputs[-1]


def test_every_mfp_mapper_command_in_the_pages_parses() -> None:
    parser_commands = [(p, c) for p, c in all_commands() if c[0] == "mfp-mapper"]
    assert len(parser_commands) > 20
    bad = []
    for page, command in parser_commands:
        try:
            build_parser().parse_args(command[1:])
        except SystemExit as stop:  # --help, --version: 0; a bad flag: 2
            if stop.code != 0:
                bad.append(f"{page.name}: {shlex.join(command)}")
    assert not bad, "commands the parser refuses:\n" + "\n".join(bad)


def launch_arguments() -> list[str]:
    text = (ROOT / "launch" / "mfp_mapper.launch.py").read_text(encoding="utf-8")
    return re.findall(r'DeclareLaunchArgument\(\s*"(\w+)"', text)


def parameter_names() -> set[str]:
    return {s.name for s in SETTINGS if s.applies in ("node", "both")}


def test_launch_lines_use_declared_arguments_and_parameters_exist() -> None:
    declared = set(launch_arguments())
    assert {"cloud_topic", "odom_topic", "params_file"} <= declared
    bad = []
    for page, command in all_commands():
        if command[:3] == ["ros2", "launch", "mfp_mapper"]:
            for word in command[4:]:
                name = word.split(":=")[0]
                if ":=" in word and name not in declared:
                    bad.append(f"{page.name}: launch argument {name}")
        if command[:3] == ["ros2", "run", "mfp_mapper"] and "-p" in command:
            for i, word in enumerate(command[:-1]):
                name = command[i + 1].split(":=")[0]
                if word == "-p" and name not in parameter_names():
                    bad.append(f"{page.name}: parameter {name}")
    assert not bad, "\n".join(bad)


def test_parameter_files_in_the_pages_name_real_parameters() -> None:
    checked = 0
    for page in pages():
        for block in code_blocks(page.read_text(encoding="utf-8"), ("yaml",)):
            data = yaml.safe_load(block)
            if not isinstance(data, dict):
                continue
            for node, section in data.items():
                if node not in ("/**", "mfp_mapper", "octomap_server"):
                    continue  # another node's file (Nav2)
                unknown = set(section["ros__parameters"]) - parameter_names()
                assert not unknown, f"{page.name}: unknown parameters {sorted(unknown)}"
                checked += 1
    assert checked >= 2


def test_the_launch_argument_table_lists_the_launch_file() -> None:
    text = (DOCS / "node.md").read_text(encoding="utf-8")
    section = text[text.index("## Launch arguments") : text.index("## Topics and services")]
    rows = re.findall(r"^\| `(\w+)` \|", section, re.MULTILINE)
    assert sorted(rows) == sorted(launch_arguments())


def test_the_drop_table_lists_every_drop_reason() -> None:
    from mfp_mapper.sensing.pipeline import DROP_REASONS

    text = (DOCS / "node.md").read_text(encoding="utf-8")
    section = text[text.index("| reason | the cloud |") :].split("\n\n")[0]
    rows = re.findall(r"^\| `(\w+)` \|", section, re.MULTILINE)
    assert sorted(rows) == sorted(DROP_REASONS)


def test_the_workspace_colcon_command_finds_both_packages(tmp_path: Path) -> None:
    """installation.md's `colcon build` line, as `colcon list` in a workspace holding this
    checkout: colcon does not look inside a package, so the interfaces need their base path."""
    pytest.importorskip("colcon_core")
    text = (DOCS / "installation.md").read_text(encoding="utf-8")
    builds = [c for c in shell_commands(text) if c[:2] == ["colcon", "build"]]
    assert builds, "installation.md gives no colcon build line"
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "mfp_mapper").symlink_to(ROOT)
    proc = subprocess.run(
        [sys.executable, "-m", "colcon", "list", "--names-only", *builds[0][2:]],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert sorted(proc.stdout.split()) == ["mfp_mapper", "mfp_mapper_msgs"]
    rosdeps = [c for c in shell_commands(text) if c[:2] == ["rosdep", "install"]]
    assert rosdeps and "src/mfp_mapper/interfaces" in rosdeps[0]


@pytest.mark.parametrize("page", ["cli.md", "node.md"])
def test_python_examples_run(page: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    blocks = list(code_blocks((DOCS / page).read_text(encoding="utf-8"), ("python",)))
    assert blocks
    for block in blocks:
        ast.parse(block)
        exec(compile(block, f"{page} example", "exec"), {"__name__": "__docs__"})


def test_docs_build_is_a_step_of_run_test() -> None:
    run = (ROOT / "run").read_text(encoding="utf-8")
    assert re.search(r'sphinx-build"? -W --keep-going -b html .*docs build/docs', run)
    assert re.search(r'step "docs[^"]*" do_docs', run)
