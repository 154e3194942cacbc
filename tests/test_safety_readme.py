"""The README's command-line examples, as written: every line parses and names files that
exist; the cheap ones run (status 0) and write what they say."""
import json
import os
import re
import shlex

import pytest

from tuning.cli import build_parser, main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: lines run for real (the rest are parsed; the --data fit of examples/record.csv is run on a
#: record of the same kind in test_tuning_cli): cheap enough for the test suite
RUN = ("diffpen simulate ball", "diffpen sweep", "diffpen fit --target-apex")


def readme_commands():
    text = open(os.path.join(ROOT, "README.md")).read()
    block = text.split("**The command line.**", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    lines = [ln.split("#", 1)[0].strip() for ln in block.splitlines()]
    return [ln for ln in lines if ln.startswith("diffpen ")]


def record_recipe():
    text = open(os.path.join(ROOT, "README.md")).read()
    m = re.search(r'`(python -c "from tuning\.sysid import[^`]*)`', text)
    return m.group(1)


def test_readme_commands_parse_and_name_existing_files():
    cmds = readme_commands()
    assert len(cmds) >= 6
    parser = build_parser()
    for cmd in cmds:
        argv = shlex.split(cmd)[1:]
        parser.parse_args(argv)                 # exits 2 on an unknown flag or bad value
        for a in argv:
            if a.startswith("examples/"):
                assert os.path.exists(os.path.join(ROOT, a)), a


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    os.symlink(os.path.join(ROOT, "examples"), tmp_path / "examples")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DIFFPEN_CACHE", "0")
    return tmp_path


def test_cheap_readme_commands_run_as_written(in_tmp, capsys):
    pytest.importorskip("matplotlib")
    ran = set()
    for cmd in readme_commands():
        if not cmd.startswith(RUN):
            continue
        ran.add(next(r for r in RUN if cmd.startswith(r)))
        rc = main(shlex.split(cmd)[1:])
        out = capsys.readouterr().out
        assert rc == 0, (cmd, out)
        if "--json" in cmd:
            res = json.loads(out.strip().splitlines()[-1])
            assert res.get("reached", True), (cmd, res)
        for a in shlex.split(cmd):
            if a.endswith((".npz", ".png")) and not a.startswith("examples/"):
                assert os.path.getsize(a) > 0, (cmd, a)
    assert ran == set(RUN)          # each kind of command ran at least once


def test_readme_record_recipe_makes_a_readable_record(in_tmp):
    code = shlex.split(record_recipe())[2]
    exec(compile(code, "README", "exec"), {})
    from tuning.sysid import load_csv
    t, z = load_csv("record.csv")
    assert t[-1] > 1.9 and len(t) == len(z) == 1000
