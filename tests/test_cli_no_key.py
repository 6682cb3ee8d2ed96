"""Every subcommand without a bus key and without a vehicle profile: one line, never a traceback (issue 26).

The subcommands are enumerated from the real argument parser (``u2sa_hw.cli.build_parser``),
so a command added later is covered without touching this file. Each runs as a real
``u2sa`` process in an empty HOME and working directory, with ``$U2SA_BUS_KEY_FILE`` naming a
file that does not exist and no ``$U2SA_VEHICLE`` (this machine has no /etc/u2sa, or the
test is skipped: an installed key or profile would be found). Arguments are harmless: a
choice is tried one by one, anything else gets a name that matches nothing; the commands
that would change this system get a staging root or a missing profile instead.
"""

from __future__ import annotations

import argparse
import os
import subprocess
from pathlib import Path

import pytest
from conftest import U2SA

from u2sa_hw.bus.key import KEY_ENV, SYSTEM_KEY
from u2sa_hw.cli import build_parser
from u2sa_hw.bus.udp_ports import private_lcm_url
from u2sa_hw.profile.loader import SYSTEM_PROFILE, VEHICLE_ENV

# Options a command gets so that it touches nothing outside the test's directory ({tmp}).
SAFE_OPTIONS: dict[str, list[str]] = {
    "install": ["--root", "{tmp}/stage"],
    "uninstall": ["--root", "{tmp}/stage"],
    "sim": ["--out", "{tmp}/sim-out"],           # its default profile is the example: see PROFILE_OPTIONS
    "mock": ["--run-dir", "{tmp}/mock"],
}
# Commands whose profile defaults to a file of this checkout rather than $U2SA_VEHICLE: they get a missing one.
PROFILE_OPTIONS: dict[str, list[str]] = {
    "sim": ["--vehicle", "{tmp}/missing/vehicle.toml"],
    "install": ["--vehicle", "{tmp}/missing/vehicle.toml"],
}


def _leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [(path, parser)]
    return [leaf for name, sub in subs[0].choices.items() for leaf in _leaves(sub, (*path, name))]


def _invocations() -> list[tuple[str, ...]]:
    """One argument list per subcommand and per choice of its first positional with choices."""
    out: list[tuple[str, ...]] = []
    for path, parser in _leaves(build_parser()):
        positionals = [a for a in parser._actions if not a.option_strings and a.nargs not in ("?", "*")]
        choice_lists = [list(a.choices) for a in positionals if a.choices]
        for choice in choice_lists[0] if choice_lists else [None]:
            words: list[str] = []
            used = False
            for action in positionals:
                if action.choices and not used:
                    words.append(str(choice))
                    used = True
                elif action.choices:
                    words.append(str(list(action.choices)[0]))
                else:
                    words.append("{tmp}/nothing" if action.dest in ("file", "dir", "source") else "nothing")
            given = {*SAFE_OPTIONS.get(path[0], []), *PROFILE_OPTIONS.get(path[0], [])}
            for action in parser._actions:   # a required option (log export --foxglove) gets a file in {tmp}
                if action.option_strings and action.required and not given & set(action.option_strings):
                    words += [action.option_strings[0], "{tmp}/out"]
            out.append((*path, *words))
    return out


INVOCATIONS = _invocations()


def test_the_enumeration_finds_every_command() -> None:
    commands = {words[0] for words in INVOCATIONS}
    assert {"status", "echo", "services", "param", "key", "log", "mission", "failsafe", "sim", "run"} <= commands
    assert ("key", "rotate") in {words[:2] for words in INVOCATIONS}


@pytest.mark.skipif(SYSTEM_KEY.exists() or SYSTEM_PROFILE.exists(),
                    reason="this machine has an installed bus key or profile, which a command would find")
@pytest.mark.parametrize("words", INVOCATIONS, ids=" ".join)
def test_no_key_and_no_profile_gives_one_line_never_a_traceback(words: tuple[str, ...], tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("U2SA_")}
    env.update(HOME=str(home), **{KEY_ENV: str(tmp_path / "missing" / "bus.key")},
               U2SA_LCM_URL=private_lcm_url(), U2SA_SIM_REALTIME="off")
    assert VEHICLE_ENV not in env
    extra = [*SAFE_OPTIONS.get(words[0], []), *PROFILE_OPTIONS.get(words[0], [])]
    args = [w.format(tmp=tmp_path) for w in (*words, *extra)]
    r = subprocess.run([*U2SA, *args], cwd=home, env=env, capture_output=True, text=True, timeout=120,
                       stdin=subprocess.DEVNULL)
    assert "Traceback" not in r.stderr, (args, r.stderr)
    if r.returncode != 0:
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("u2sa"), (args, r.returncode, r.stderr)
