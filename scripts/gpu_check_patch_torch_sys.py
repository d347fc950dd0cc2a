"""Stubs the functions of torch-sys's generated C++ wrapper that a libtorch other than the one a
tch release targets does not declare (tch 0.26 against torch 2.11's headers).

Usage: gpu_check_patch_torch_sys.py SRC_TORCH_SYS DST_DIR LIBTORCH

Copies the torch-sys crate SRC to DST, then compiles DST/libtch/torch_api_generated.cpp with
`-fsyntax-only` against LIBTORCH's headers and replaces the body of every wrapper function the
compiler rejects with a throw (caught by the wrapper's PROTECT macro, so a call returns a Rust
error naming the op instead of failing to link). Repeats until the file compiles. Only ops this
libtorch lacks are affected; the trainer calls none of them.
"""

import re
import shutil
import subprocess
import sys
from pathlib import Path

# The wrapper's functions start at column 0 with their C signature and end at a lone "}".
FUNCTION = re.compile(r"^[a-z].*\b(atg_\w+)\(.*\{$")
# gcc names the failing wrapper in its "In function 'void atg_x(...)'" line.
IN_FUNCTION = re.compile(r"In function '[^']*\b(atg_\w+)\(")
ERROR_LINE = re.compile(r"torch_api_generated\.cpp:(\d+):\d+: error")


def failing_functions(source: Path, libtorch: Path) -> set[str]:
    include = libtorch / "include"
    command = [
        "g++", "-std=c++17", "-fsyntax-only", "-w", "-D_GLIBCXX_USE_CXX11_ABI=1",
        "-I", str(include), "-I", str(include / "torch/csrc/api/include"), str(source),
    ]
    result = subprocess.run(command, capture_output=True, text=True, cwd=source.parent)
    if result.returncode == 0:
        return set()
    names = set(IN_FUNCTION.findall(result.stderr))
    lines = source.read_text().splitlines()
    # Errors outside an "In function" note: map the line back to its enclosing wrapper.
    for number in ERROR_LINE.findall(result.stderr):
        for i in range(int(number) - 1, -1, -1):
            match = FUNCTION.match(lines[i])
            if match:
                names.add(match.group(1))
                break
    if not names:
        sys.exit("torch_api_generated.cpp fails outside any wrapper function:\n" + result.stderr[-4000:])
    return names


def stub(source: Path, names: set[str]) -> None:
    out, lines, i = [], source.read_text().splitlines(), 0
    while i < len(lines):
        match = FUNCTION.match(lines[i])
        if match and match.group(1) in names:
            out.append(lines[i])
            out.append("  PROTECT(")
            out.append(f'    throw std::runtime_error("{match.group(1)}: not in this libtorch (stubbed by gpu_check)");')
            out.append("  )")
            i += 1
            while lines[i] != "}":
                # Non-void wrappers return a value after PROTECT; keep a neutral return.
                if lines[i].strip().startswith("return"):
                    out.append("  return 0;")
                i += 1
            out.append("}")
        else:
            out.append(lines[i])
        i += 1
    source.write_text("\n".join(out) + "\n")


def main() -> None:
    src, dst, libtorch = (Path(a).resolve() for a in sys.argv[1:4])
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    source = dst / "libtch" / "torch_api_generated.cpp"
    stubbed: set[str] = set()
    for _ in range(5):
        names = failing_functions(source, libtorch)
        if not names:
            break
        stub(source, names)
        stubbed |= names
    else:
        sys.exit("torch_api_generated.cpp still fails after 5 passes")
    print(f"stubbed {len(stubbed)} wrapper functions: {', '.join(sorted(stubbed))}")


if __name__ == "__main__":
    main()
