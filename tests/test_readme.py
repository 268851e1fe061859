"""The README's Quick use blocks run as written (a README sentence no command backs is a defect)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _quick_use_blocks() -> list[str]:
    text = README.read_text()
    section = text.split("## Quick use", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_quick_use_has_blocks() -> None:
    assert len(_quick_use_blocks()) >= 2


@pytest.mark.parametrize("index", range(2))
def test_quick_use_block_runs(index: int, tmp_path, monkeypatch, capsys) -> None:
    block = _quick_use_blocks()[index]
    monkeypatch.chdir(tmp_path)
    exec(compile(block, f"README quick use {index}", "exec"), {"__name__": "__readme__"})
    printed = capsys.readouterr().out
    assert printed.strip()
    if index == 1:
        assert "finished [True, True, True, True, True, True, True]" in printed and "stability True" in printed
        assert (tmp_path / "mm3_library" / "manifest.json").is_file()
    else:
        assert "certified True" in printed and os.path.isfile(tmp_path / "sshape_lpvds.pt")
