"""Every option the README and docs/ name is one a command takes: a renamed or removed flag left in
the docs fails here (tests/test_docs_links.py does the same for links and cited tests)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FLAG = re.compile(r"(?<![\w/.-])--[a-z][a-z0-9_]*(?:[.-][a-z0-9_]+)*")

# Options of other tools the docs show, and names the docs give as history (each says so where it stands).
OTHER_TOOLS = {
    "--durations", "--timeout", "--hypothesis-profile", "--hypothesis-show-statistics",  # pytest
    "--address", "--head",  # ray start
    "--use_fast_math",  # nvcc
}
HISTORY = {
    "--adams": "bench/train_step_bench.py's option since renamed --variants fused-adam (docs/rasterizer.md says so)",
    "--plane.visibility-check": "commit 4a93cdf, reverted (docs/training.md, docs/ablation_results.md say so)",
}


def _help_flags(capsys, monkeypatch) -> set[str]:
    from cli.evaluate_cli import COMMANDS as evaluate_commands
    from cli.evaluate_cli import main as evaluate
    from cli.geocues_cli import COMMANDS as geocues_commands
    from cli.geocues_cli import main as geocues
    from cli.splat_cli import COMMANDS as splat_commands
    from cli.splat_cli import main as splat

    monkeypatch.setenv("COLUMNS", "300")  # no flag wrapped or cut by the help's box
    flags: set[str] = set()
    for main, commands in ((geocues, geocues_commands), (splat, splat_commands), (evaluate, evaluate_commands)):
        for name in commands:
            assert main([name, "--help"]) == 0
            flags |= set(FLAG.findall(capsys.readouterr().out))
    return flags


def _known(flag: str, commands: set[str], scripts: str) -> bool:
    if flag in commands or flag in OTHER_TOOLS or flag in HISTORY:
        return True
    if any(c.startswith(flag + ".") for c in commands):  # a group, as in `--tsdf.*`
        return True
    if flag.startswith("--train.") and "--" + flag[len("--train."):] in commands:  # bench/train_bench.py
        return True
    if re.search(re.escape(flag) + r"(?![\w-])", scripts):  # a bench or setup script's argparse option
        return True
    field = flag[2:].replace("-", "_")  # a bench script's tyro dataclass field (`camera_opt: bool = False`)
    return re.search(r"^\s+" + re.escape(field) + r"\s*:", scripts, re.M) is not None


def test_every_option_the_docs_name_exists(capsys, monkeypatch):
    commands = _help_flags(capsys, monkeypatch)
    assert {"--strategy.max-gaussians", "--floor.lines", "--gt", "--preset"} <= commands  # the help was read
    scripts = "\n".join(p.read_text() for d in ("bench", "scripts") for p in sorted((ROOT / d).iterdir())
                        if p.suffix in (".py", ".sh"))
    unknown = [f"{page.relative_to(ROOT)}:{i}: {flag}" for page in PAGES
               for i, line in enumerate(page.read_text().splitlines(), 1)
               for flag in FLAG.findall(line) if not _known(flag, commands, scripts)]
    assert not unknown, "options no command or script takes:\n" + "\n".join(unknown)


@pytest.mark.parametrize("flag, known", [("--tsdf", True), ("--train.iters", True), ("--strategy.max-gausians", False),
                                         ("--train.no-such-option", False), ("--adams", True), ("--other", False),
                                         ("--other-option", True), ("--camera-opt", True), ("--camera", False)])
def test_the_check_tells_a_missing_option(flag, known):
    commands = {"--tsdf.voxel-size", "--iters", "--strategy.max-gaussians"}
    scripts = 'ap.add_argument("--other-option")\nclass Bench:\n    camera_opt: bool = False\n'
    assert _known(flag, commands, scripts) is known
