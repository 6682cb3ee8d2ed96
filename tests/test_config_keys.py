"""Unknown keys and did-you-mean (u2sa_hw/config/keys.py)."""

from __future__ import annotations

from u2sa_hw.config.keys import did_you_mean, unknown_key_problems


def test_did_you_mean_finds_a_typo_and_a_case_slip() -> None:
    assert did_you_mean("prot", ["port", "baudrate"]) == "did you mean 'port'?"
    assert did_you_mean("log_levle", ["log_level", "name"]) == "did you mean 'log_level'?"
    assert did_you_mean("path_planer", ["path_planner", "control"]) == "did you mean 'path_planner'?"
    assert did_you_mean("PORT", ["port"]) == "did you mean 'port'?"


def test_did_you_mean_says_nothing_without_a_close_choice() -> None:
    assert did_you_mean("zzz", ["port", "baudrate"]) == ""
    assert did_you_mean("port", []) == ""


def test_unknown_key_problems_one_line_per_unknown_key() -> None:
    problems = unknown_key_problems({"prot": 1, "port": 2, "qqq": 3}, ["port", "baudrate"],
                                    where="v.toml [services.gps] settings")
    assert problems == [
        "v.toml [services.gps] settings: unknown key 'prot'; did you mean 'port'? (known: baudrate, port)",
        "v.toml [services.gps] settings: unknown key 'qqq' (known: baudrate, port)",
    ]
    assert unknown_key_problems({"port": 1}, ["port"], where="x") == []
