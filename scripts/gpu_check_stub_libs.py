"""Collects the shared libraries the gpu_check bundle must carry, within 64 MiB.

Usage: gpu_check_stub_libs.py OUT_LIB_DIR LIBTORCH_LIB BINARY...

The binaries link Debian's FFmpeg, whose full dependency closure is about 230 MB (xz: 75 MB), more
than travels with a call. The check only encodes and decodes one H.264 mp4 (datagen synth, pairs),
so the bundle carries the FFmpeg libraries that work does (REAL below) as they are, and replaces
every other library they or the binaries name (codecs, X11, SDL, GnuTLS, ...) by a small stub with
the same soname that defines exactly the symbols (and symbol versions) its users import. FFmpeg is
linked with BIND_NOW, so every imported function must exist at load time; a stub function that is
ever called prints which function of which library is missing and aborts, so a path that needs a
dropped library fails loudly instead of misbehaving. Libraries every Linux has (glibc, libstdc++,
libgcc_s, zlib) and those of the torch wheel and its nvidia wheels are left to the machine.
"""

import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

# FFmpeg's libraries that decoding and encoding an mp4 runs through, and the x264 encoder datagen
# picks first; they are carried unchanged.
REAL = {
    "libavcodec.so.59", "libavformat.so.59", "libavutil.so.57", "libswscale.so.6", "libswresample.so.4",
    "libx264.so.164",
    # Its demuxer's probe, run on every input, dereferences what gme_identify_header returns.
    "libgme.so.0",
    # Parquet's zstd codec (Debian's libzstd: see .cargo/config.toml): every shard write and read.
    "libzstd.so.1",
}
# Stub functions that may be called and return 0 (nothing, NULL, "not recognized"): ffmpeg-next's
# init() registers the capture devices (never opened); looking an encoder up by name runs every
# codec's static init, which asks libaom, libvpx and x265 for their versions and capabilities; opening
# an input probes every demuxer, libopenmpt's included. Found by running synth and pairs on stubs.
NO_OPS = {"avdevice_register_all", "aom_codec_version", "aom_codec_av1_cx", "aom_codec_get_caps", "vpx_codec_vp9_cx", "vpx_codec_get_caps", "x265_api_get_199", "openmpt_probe_file_header_without_filesize"}
# Provided by the machine: glibc, the C++ runtime, the dynamic loader, and zlib, which its Python
# needs and the torch wheel's cuDNN links (a stub first on LD_LIBRARY_PATH would shadow it there).
SYSTEM = re.compile(r"^(libc|libm|libdl|librt|libpthread|libresolv|libutil|libgcc_s|libstdc\+\+|libz|ld-linux[-\w]*)\.so")
# readelf --dyn-syms -W: "Num: Value Size Type Bind Vis Ndx Name[@[@]VERSION] [(n)]"
SYMBOL = re.compile(r"^\s*\d+:\s+[0-9a-f]+\s+(\d+|0x[0-9a-f]+)\s+(\w+)\s+(\w+)\s+\w+\s+(\w+)\s+(\S+)")


def needed(path: Path) -> list[str]:
    out = subprocess.run(["readelf", "-d", "-W", str(path)], capture_output=True, text=True, check=True).stdout
    return re.findall(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]", out)


def symbols(path: Path) -> list[tuple[str, str, str, int, str, str | None]]:
    """(section index, type, bind, size, name, version) of each dynamic symbol."""
    out = subprocess.run(["readelf", "--dyn-syms", "-W", str(path)], capture_output=True, text=True, check=True).stdout
    rows = []
    for line in out.splitlines():
        match = SYMBOL.match(line)
        if not match:
            continue
        size, kind, bind, ndx, name = match.groups()
        version = None
        if "@" in name:
            name, version = re.split(r"@@?", name, maxsplit=1)
        rows.append((ndx, kind, bind, int(size, 0), name, version))
    return rows


def version_names(path: Path) -> list[str]:
    """The version names PATH defines (its .gnu.version_d, less the soname entry)."""
    out = subprocess.run(["readelf", "-V", "-W", str(path)], capture_output=True, text=True, check=True).stdout
    section = out.split("Version needs section")[0]
    return re.findall(r"Flags: (?!BASE)[\w ]+?\s+Index: \d+\s+Cnt: \d+\s+Name: (\S+)", section)


def resolve(libtorch_lib: Path, binaries: list[Path]) -> dict[str, Path]:
    """Soname to path of every library the binaries load, as the loader finds them here."""
    env = {"LD_LIBRARY_PATH": str(libtorch_lib), "PATH": "/usr/bin:/bin"}
    found: dict[str, Path] = {}
    for binary in binaries:
        out = subprocess.run(["ldd", str(binary)], capture_output=True, text=True, check=True, env=env).stdout
        for soname, path in re.findall(r"^\s*(\S+) => (/\S+)", out, re.M):
            found[soname] = Path(path)
    return found


def carried_by_machine(soname: str, path: Path) -> bool:
    return bool(SYSTEM.match(soname)) or "/torch/lib/" in str(path) or "/nvidia/" in str(path)


def write_stub(soname: str, library: Path, users: list[Path], out_dir: Path, work: Path) -> int:
    """Builds OUT_DIR/SONAME defining what USERS import from LIBRARY; returns the symbol count."""
    defined = {}
    for ndx, kind, bind, size, name, version in symbols(library):
        if ndx != "UND" and bind in ("GLOBAL", "WEAK") and kind in ("FUNC", "IFUNC", "OBJECT", "TLS"):
            defined.setdefault(name, (kind, size, version))
    # The version each user asks for (a library may define one name under several versions).
    imported: dict[str, str | None] = {}
    for user in users:
        for ndx, _, _, _, name, version in symbols(user):
            if ndx == "UND" and (imported.get(name) is None):
                imported[name] = version
    wanted = sorted(imported.keys() & defined.keys())
    lines = [
        "#include <stdio.h>",
        "#include <stdlib.h>",
        "static void missing(const char *name) {",
        f'  fprintf(stderr, "gpu_check: %s of {soname} called, but the bundle carries only a stub of it\\n", name);',
        "  abort();",
        "}",
    ]
    nodes: dict[str | None, list[str]] = {}
    for i, name in enumerate(wanted):
        kind, size, version = defined[name]
        version = imported[name] or version
        nodes.setdefault(version, []).append(name)
        if kind in ("FUNC", "IFUNC"):
            body = "return 0;" if name in NO_OPS else f'missing("{name}"); return 0;'
            lines.append(f'long stub_{i}(void) __asm__("{name}");')
            lines.append(f"long stub_{i}(void) {{ {body} }}")
        else:
            storage = "__thread " if kind == "TLS" else ""
            lines.append(f'{storage}char data_{i}[{max(size, 1)}] __asm__("{name}");')
            lines.append(f"{storage}char data_{i}[{max(size, 1)}] = {{0}};")
    source = work / f"{soname}.c"
    source.write_text("\n".join(lines) + "\n")
    command = ["gcc", "-shared", "-fPIC", "-O1", "-w", "-o", str(out_dir / soname), str(source), f"-Wl,-soname,{soname}"]
    # Users check at load time that every version name of the library they were linked against
    # exists, including names none of their symbols carry.
    for version in version_names(library):
        nodes.setdefault(version, [])
    if any(version is not None for version in nodes):
        script = work / f"{soname}.map"
        blocks = []
        for version, names in nodes.items():
            body = f"global: {' '.join(f'{n};' for n in names)}" if names else ""
            blocks.append(f"{version or 'STUB_UNVERSIONED'} {{ {body} }};")
        script.write_text("\n".join(blocks) + "\n")
        command.append(f"-Wl,--version-script={script}")
    subprocess.run(command, check=True)
    return len(wanted)


def main() -> None:
    out_dir, libtorch_lib = Path(sys.argv[1]), Path(sys.argv[2])
    binaries = [Path(b) for b in sys.argv[3:]]
    out_dir.mkdir(parents=True, exist_ok=True)
    found = resolve(libtorch_lib, binaries)
    missing_real = REAL - found.keys()
    if missing_real:
        sys.exit(f"the binaries do not load {sorted(missing_real)}: update REAL in {sys.argv[0]}")
    for soname in sorted(REAL):
        shutil.copy2(found[soname], out_dir / soname)
    # Everything the binaries and the real libraries name directly; what those name in turn is
    # never loaded, since a stub needs nothing.
    users = binaries + [out_dir / s for s in sorted(REAL)]
    stubs: dict[str, list[Path]] = {}
    for user in users:
        for soname in needed(user):
            if soname in REAL or soname not in found or carried_by_machine(soname, found[soname]):
                continue
            stubs.setdefault(soname, []).append(user)
    with tempfile.TemporaryDirectory() as work:
        for soname, its_users in sorted(stubs.items()):
            count = write_stub(soname, found[soname], its_users, out_dir, Path(work))
            print(f"stub {soname}: {count} symbols for {', '.join(u.name for u in its_users)}")
    print(f"real: {', '.join(sorted(REAL))}")


if __name__ == "__main__":
    main()
