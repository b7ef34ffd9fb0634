"""The Makefile's order, read from make's database: nothing makes, installs into or runs a venv before the
Debian packages are installed (tests/house/makefile_order.py says why a machine that ran make once never
sees the defect)."""

from __future__ import annotations

import re

import pytest

from .makefile_order import MAKEFILE, apt_targets, database, unordered_venv_uses, venvs


def test_every_venv_use_waits_for_the_debian_packages():
    assert unordered_venv_uses() == []


def test_the_database_sees_the_venvs_and_the_apt_target():
    """The check is only as good as what it reads: the four venvs the Makefile makes and its apt target."""
    rules, _ = database()
    assert venvs(rules) == {".venv", ".venv-engines", ".venv-genesis", ".venv-peers"}
    assert apt_targets(rules) == {"apt"}


def test_the_check_fails_on_the_makefile_that_failed_a_fresh_machine(tmp_path):
    """The rules as they were when a fresh Debian 12 machine's first ``make test`` ran pip beside
    apt-get (venv and install waiting for nothing but each other): both targets are named."""
    text = MAKEFILE.read_text()
    text = text.replace("$(VENV)/bin/python: | apt\n", "$(VENV)/bin/python:\n")
    text = text.replace(
        "$(STAMP): pyproject.toml | apt $(VENV)/bin/python", "$(STAMP): pyproject.toml | $(VENV)/bin/python"
    )
    assert "| apt $(VENV)" not in text and "python: | apt" not in text, "the rules moved: update this test"
    (tmp_path / "Makefile").write_text(text)
    found = unordered_venv_uses(tmp_path / "Makefile")
    assert any(line.startswith(".venv/bin/python: /usr/bin/python3 -m venv") for line in found), found
    assert any(line.startswith(".venv/.tissuebench-installed: .venv/bin/python -m pip install") for line in found), (
        found
    )


@pytest.mark.parametrize(
    ("rule", "target"),
    [
        ("$(VENV)/bin/python: | apt", ".venv/bin/python"),
        ("$(ENGINES_STAMP): adapters/requirements.txt | apt", ".venv-engines/.tissuebench-installed"),
    ],
)
def test_each_venv_rules_wait_is_seen_when_removed(tmp_path, rule, target):
    """The rules that make a venv wait for apt themselves (the project's install waits through its venv):
    with apt taken out of one, the check names that target."""
    text = MAKEFILE.read_text()
    assert text.count(rule + "\n") == 1, f"the rule {rule!r} moved: update this test"
    cut = re.sub(r"\s*\|\s*$", "", rule.replace(" apt", "").replace("| |", "|"))
    (tmp_path / "Makefile").write_text(text.replace(rule + "\n", cut + "\n"))
    found = unordered_venv_uses(tmp_path / "Makefile")
    assert found and all(line.startswith(target + ": ") for line in found), (cut, found)
