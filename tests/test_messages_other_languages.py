"""Our LCM types in C, C++ and Java: lcm-gen's output for every .lcm file must compile.

A field named like a keyword of one of LCM's languages (``register`` in C and C++) makes that
language's generated code fail to build; nothing else would notice. The lcm wheel ships
lcm-gen, the C/C++ headers and lcm.jar; a compiler that is not installed skips its language
with the reason.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from u2sa_hw import message_codegen

SITE = Path(sys.executable).resolve().parent.parent / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / \
    "site-packages"


def _wheel_file(*parts: str) -> Path:
    """A file the lcm wheel installs beside the packages (include/, share/java/)."""
    import lcm

    for base in (Path(lcm.__file__).resolve().parent.parent, SITE):
        path = base.joinpath(*parts)
        if path.exists():
            return path
    pytest.skip(f"the lcm wheel's {'/'.join(parts)} was not found (pip install lcm ships it)")


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"{name} is not installed: its language's generated code is not compiled")
    return path


def _gen(flag: str, *options: str) -> None:
    subprocess.run([message_codegen.find_lcm_gen(), flag, *options, *map(str, message_codegen.lcm_sources())],
                   check=True, capture_output=True)


def _compiled(cmd: list[str], *, cwd: Path) -> None:
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    assert r.returncode == 0, f"{' '.join(cmd[:2])} ... failed:\n{r.stderr[-4000:]}"


def test_every_type_compiles_in_c(tmp_path: Path) -> None:
    gcc = _tool("gcc")
    include = _wheel_file("include", "lcm", "lcm.h").parent.parent
    _gen("-c", "--c-cpath", str(tmp_path), "--c-hpath", str(tmp_path))
    sources = sorted(str(p) for p in tmp_path.glob("*.c"))
    assert len(sources) == len(list(message_codegen.GENERATED_DIR.glob("[A-Z]*.py")))
    _compiled([gcc, "-std=c99", "-Wall", "-Werror", "-c", f"-I{include}", f"-I{tmp_path}", *sources], cwd=tmp_path)


def test_every_type_compiles_in_cpp(tmp_path: Path) -> None:
    gxx = _tool("g++")
    include = _wheel_file("include", "lcm", "lcm_coretypes.h").parent.parent
    _gen("-x", "--cpp-hpath", str(tmp_path))
    headers = sorted(tmp_path.rglob("*.hpp"))
    assert headers
    unit = tmp_path / "all_types.cpp"
    lines = [f'#include "{h.relative_to(tmp_path)}"' for h in headers]
    lines += ["#include <vector>", "int main() {", "    std::vector<char> buf(1 << 16);"]
    for i, h in enumerate(headers):   # encode and decode each type, so every template is instantiated
        name = "::".join(h.relative_to(tmp_path).with_suffix("").parts)
        lines += [f"    {{ {name} m{i}; int n = m{i}.getEncodedSize(); m{i}.encode(buf.data(), 0, n);",
                  f"      m{i}.decode(buf.data(), 0, n); }}"]
    lines += ["    return 0;", "}"]
    unit.write_text("\n".join(lines) + "\n")
    _compiled([gxx, "-std=c++11", "-Wall", "-Werror", "-c", f"-I{include}", f"-I{tmp_path}", str(unit)], cwd=tmp_path)


def test_every_type_compiles_in_java(tmp_path: Path) -> None:
    javac = _tool("javac")
    jar = _wheel_file("share", "java", "lcm.jar")
    _gen("-j", "--jpath", str(tmp_path))
    sources = sorted(str(p) for p in tmp_path.rglob("*.java"))
    assert sources
    _compiled([javac, "-nowarn", "-cp", str(jar), "-d", str(tmp_path / "classes"), *sources], cwd=tmp_path)
