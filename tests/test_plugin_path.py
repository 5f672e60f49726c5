"""The plugin author's path, end to end: every `$` command of docs/adding-a-method.md's
walkthrough runs, in order, in a fresh folder and a fresh virtual environment that sees this
one's packages (so installing the scaffold leaves the test environment untouched), and does
what the page says: the scaffold installs, is listed, conforms, runs a sweep cell, and
passes its own canary gate."""
import os
import re
import subprocess
import sys
import sysconfig

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOC = os.path.join(ROOT, "docs", "adding-a-method.md")


def walkthrough_commands() -> list[str]:
    """The `$ ` lines of the ```console blocks of the walkthrough, in order."""
    text = open(DOC).read()
    section = text.split("## The walkthrough", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```console\n(.*?)```", section, re.S)
    return [line[2:] for block in blocks for line in block.splitlines() if line.startswith("$ ")]


def _child_env(tmp_path) -> dict:
    """A venv whose site-packages adds this interpreter's (a .pth line), with `pip`,
    `ildbench` and `python` on PATH running inside it."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    child_site = subprocess.run([str(venv / "bin" / "python"), "-c",
                                 "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                check=True, capture_output=True, text=True).stdout.strip()
    parent_site = sysconfig.get_paths()["purelib"]
    with open(os.path.join(child_site, "_parent.pth"), "w") as f:
        f.write(f"import site; site.addsitedir({parent_site!r})\n")
    python = venv / "bin" / "python"
    for name, run in (("pip", "-m pip"), ("ildbench", "-m bench.cli")):
        path = venv / "bin" / name
        path.write_text(f'#!/bin/sh\nexec "{python}" {run} "$@"\n')
        path.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "ILDBENCH_STORE")}
    env.update(PATH=f"{venv / 'bin'}:{env['PATH']}", PIP_NO_BUILD_ISOLATION="0",
               PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    return env


def test_the_walkthrough_lists_the_whole_path():
    cmds = walkthrough_commands()
    assert cmds[0] == "ildbench new-method mymethod"
    assert [c.split()[1] for c in cmds if c.startswith("ildbench")] == [
        "new-method", "methods", "conform", "sweep", "leaderboard", "check", "check"]
    assert any(c.startswith("pip install -e") for c in cmds)


def test_the_commands_of_adding_a_method_make_a_plugin_that_conforms_sweeps_and_gates(
        tmp_path):
    env = _child_env(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    out = {}
    for cmd in walkthrough_commands():
        proc = subprocess.run(cmd, shell=True, cwd=work, env=env, capture_output=True,
                              text=True, timeout=600)
        assert proc.returncode == 0, f"`{cmd}` failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        out[cmd] = proc.stdout
    listed = next(v for k, v in out.items() if k == "ildbench methods")
    assert "mymethod" in listed and "entry point mymethod" in listed
    conform = next(v for k, v in out.items() if k.startswith("ildbench conform"))
    assert "verdict: PASS" in conform
    sweep = next(v for k, v in out.items() if k.startswith("ildbench sweep"))
    assert "mymethod on pointmass seed 0: ok" in sweep
    assert (work / "report" / "leaderboard.md").read_text().count("mymethod") >= 1
    assert (work / "ildbench-mymethod" / "canary_reference.json").exists()
    gate = [v for k, v in out.items() if k.startswith("ildbench check")][-1]
    assert "mymethod/pointmass" in gate and "canary gate: PASS" in gate
    assert "2 passed" in next(v for k, v in out.items() if "pytest" in k)
    # the test environment itself never saw the plugin
    from bench.plugins import all_methods
    assert "mymethod" not in all_methods()


@pytest.mark.parametrize("name, message", [
    ("My-Method", "must be lower case letters"),
    ("class", "must be lower case letters"),
    ("bc", "already registered"),
])
def test_new_method_refuses_a_bad_name(tmp_path, capsys, name, message):
    from bench.cli import main
    assert main(["new-method", name, "--dir", str(tmp_path / "x")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_new_method_refuses_a_folder_that_holds_files(tmp_path, capsys):
    from bench.cli import main
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    assert main(["new-method", "fresh", "--dir", str(tmp_path / "x")]) == 2
    assert "exists and is not an empty folder" in capsys.readouterr().err
    assert os.listdir(tmp_path / "x") == ["keep.txt"]
