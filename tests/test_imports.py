"""No import cycles between the project's modules (STYLE.md): every `from geocues/splat/evaluation/cli
... import` — module-level or inside a function, but not under TYPE_CHECKING — forms a DAG."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("geocues", "splat", "evaluation", "cli")


def _imports() -> dict[str, set[str]]:
    graph = {}
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*.py"):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
            tree = ast.parse(path.read_text())
            skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                    and "TYPE_CHECKING" in ast.unparse(node.test) for n in ast.walk(node)}
            deps = set()
            for node in ast.walk(tree):
                if id(node) in skip:
                    continue
                if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    deps.add(node.module)
                elif isinstance(node, ast.Import):
                    deps.update(a.name for a in node.names)
            graph[name] = {d for d in deps if d.split(".")[0] in PACKAGES and d != name}
    return graph


def test_no_import_cycles():
    graph = _imports()
    assert "splat.train" in graph and "splat.contracts" in graph
    state: dict[str, int] = {}  # 1 = on the stack, 2 = done
    cycles = []

    def visit(node, stack):
        state[node] = 1
        for dep in sorted(graph.get(node, ())):
            if dep not in graph:
                continue
            if state.get(dep) == 1:
                cycles.append(stack[stack.index(dep):] + [dep])
            elif dep not in state:
                visit(dep, stack + [dep])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_usage_lines_are_whole_sentences():
    """`geocues --help`: each command's first sentence, not its docstring's first line cut mid-phrase."""
    from cli._dispatch import summary

    assert summary("The paper's ablation (Tab. 3) on SCENE: one run\n    per row. More.") == \
        "The paper's ablation (Tab. 3) on SCENE: one run per row."
    assert summary("Priors for a real scene (e.g. ICL-NUIM).\n\nArgs: x") == "Priors for a real scene (e.g. ICL-NUIM)."
    long = summary("word " * 40 + "end.")
    assert long.endswith(" ...") and len(long) <= 104


def test_console_scripts_exist_and_a_ctrl_c_while_starting_is_one_line(monkeypatch, capsys):
    """pyproject's scripts name callables that exist; a Ctrl-C while a command table imports torch &
    co. (about two seconds) ends with one line and 130, not a traceback of the import."""
    import importlib
    import signal
    import tomllib

    import cli.entry as entry

    monkeypatch.setattr(signal, "signal", lambda *a: None)  # the scripts catch SIGTERM: not in pytest's process

    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert sorted(scripts) == ["evaluate", "geocues", "splat"]
    for target in scripts.values():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), target

    def interrupted(name):
        raise KeyboardInterrupt

    monkeypatch.setattr(entry.importlib, "import_module", interrupted)
    assert entry.splat() == 130
    assert capsys.readouterr().err.strip() == "splat: interrupted while starting"

    class Module:  # imported; the signal comes while the command parses (before its own handling)
        @staticmethod
        def main():
            raise KeyboardInterrupt("SIGTERM")

    monkeypatch.setattr(entry.importlib, "import_module", lambda name: Module)
    assert entry.geocues() == 143  # a SIGTERM then was a traceback (Ctrl-C) or a silent death
    assert capsys.readouterr().err.strip() == "geocues: interrupted while starting"


def test_a_sigterm_while_a_command_starts_is_one_line_and_143(tmp_path):
    """The real process: a SIGTERM while a command table imports torch & co. (the first ~2 s) killed it
    without a word, a Ctrl-C there was a traceback of pycolmap's import; now one line and 143 (130).
    The command table here sleeps while imported, so the signal lands in the import every time."""
    import signal
    import subprocess
    import sys
    import time

    (tmp_path / "slow_table.py").write_text("import time\ntime.sleep(30)\n\ndef main():\n    return 0\n")
    code = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler)\n"  # as in a terminal: a
            "from cli.entry import _run; sys.exit(_run('geocues', 'slow_table'))")  # job started with & ignores it
    env = {**__import__("os").environ, "PYTHONPATH": f"{tmp_path}{__import__('os').pathsep}{REPO}"}
    for sig, rc in ((signal.SIGTERM, 143), (signal.SIGINT, 130)):
        p = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(2.0)  # python is up and importing the (sleeping) command table
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
        assert p.returncode == rc and err.strip() == "geocues: interrupted while starting", (sig, p.returncode, err[-500:])
