"""No user text reaches a CalculiX keyword line: model and part names from model.yaml are checked against ccx's name
rules or replaced by generated ones."""

from __future__ import annotations

import dataclasses
import re

import pytest

from hood_decomp.core.fe.calculix import ccx_names, load_cases, run_job, write_deck
from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.io.mesh import read_inp_mesh

INJECTION = "skin\n*INCLUDE, INPUT=/etc/passwd\n**"
#: the only keyword lines write_deck may produce, with ccx names in their options
KEYWORD = re.compile(r"\*(HEADING|NODE|ELEMENT|MATERIAL|ELASTIC|DENSITY|SHELL SECTION|STEP|STATIC|BOUNDARY|CLOAD|"
                     r"NODE PRINT|END STEP)(, [A-Z]+=[A-Za-z][A-Za-z0-9_-]{0,79})*")
NUMBERS = re.compile(r"[-+0-9.eE,]+|U")  # node, element, boundary, load and material lines; "U" of *NODE PRINT


@pytest.fixture(scope="module")
def hostile_model():
    """The 20 x 20 hood with its parts renamed (patches and skin_part follow) to names ccx must not see."""
    model = build_hood(grid=(20, 20))
    hostile = [INJECTION, "inner panel", "OUTER_SKIN", "PART_0"]
    rename = {p.name: hostile[i] if i < len(hostile) else p.name for i, p in enumerate(model.parts)}
    boundaries = tuple(dataclasses.replace(b, patch=dataclasses.replace(
        b.patch, parts=tuple(rename[n] for n in b.patch.parts),
        exclude_parts=tuple(rename[n] for n in b.patch.exclude_parts))) for b in model.boundaries)
    return dataclasses.replace(model, name="hood\n*INCLUDE, INPUT=/etc/shadow", boundaries=boundaries,
                               parts=tuple(dataclasses.replace(p, name=rename[p.name]) for p in model.parts),
                               skin_part=rename[model.skin_part])


def test_no_deck_line_comes_from_user_text(hostile_model, tmp_path):
    """Fails if a model or part name holding a newline and *INCLUDE (or a space, or a name that another part's
    upper-cased name or a generated name collides with) reaches the deck: every line must be a known keyword line
    with ccx names, a number line, or the filtered heading."""
    cases, constrained = load_cases(hostile_model)
    text = write_deck(hostile_model, cases[1], constrained, tmp_path / "deck.inp").read_text()
    lines = text.splitlines()
    assert not any(line.lstrip().upper().startswith("*INCLUDE") for line in lines) and "/" not in text
    heading = lines.index("*HEADING") + 1
    assert re.fullmatch(r"hood_decomp [A-Za-z0-9_.-]+ [A-Za-z0-9_.-]+", lines[heading])
    for number, line in enumerate(lines):
        if number != heading and line:
            assert KEYWORD.fullmatch(line) or NUMBERS.fullmatch(line), f"line {number + 1}: {line!r}"
    _, _, elsets = read_inp_mesh(tmp_path / "deck.inp")
    kept = [p.name for p in hostile_model.parts[4:]]
    assert set(elsets) <= {"PART_0", "PART_1", "OUTER_SKIN", "PART_3", *kept} and "PART_0" in elsets


def test_ccx_names_keeps_good_names_and_replaces_the_rest():
    """Fails if a valid unique name is renamed, or a name ccx would misread (space, comma, '=', newline, leading digit,
    over 80 characters, a case-insensitive duplicate, a clash with a generated name) is kept."""
    names = ["outer_skin", "inner-panel", "a b", "x,y", "k=v", "1st", "L" * 81, "Dup", "DUP", "P1", "line\n*END"]
    assert ccx_names(names, "P") == ["outer_skin", "inner-panel", "P2", "P3", "P4", "P5", "P6", "P7", "P8", "P9",
                                     "P10"]


def test_a_job_name_cannot_leave_its_directory(tmp_path):
    """Fails if a load case name (made from a parameter label) with a path separator makes run_job write or read a
    file outside its temporary directory; a fake ccx that records its arguments and working directory stands in."""
    fake = tmp_path / "ccx"
    fake.write_text("#!/bin/sh\npwd > \"$0.cwd\"; echo \"$2\" > \"$0.arg\"; exit 1\n")
    fake.chmod(0o755)
    with pytest.raises(Exception, match="ccx job"):
        run_job("*HEADING\n", "unit_../../escape", 1, workdir=str(tmp_path), executable=str(fake))
    assert "/" not in (tmp_path / "ccx.arg").read_text().strip()
    assert not (tmp_path / "escape.inp").exists() and not list(tmp_path.parent.glob("escape*"))
