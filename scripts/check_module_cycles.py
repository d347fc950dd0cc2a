#!/usr/bin/env python3
"""Finds import cycles among the modules of Rust crates, and uses that break the layer rules a
document states: exits 1 listing them, 0 when none.

Usage: check_module_cycles.py [--layers DOC.md] CRATE_SRC_DIR...   (e.g. datagen/src trainer/src)
       check_module_cycles.py --layers DOC.md --workspace Cargo.toml   (every member crate's src/)
       check_module_cycles.py --self-test          (the checker on small crates it writes)

Layers (`--layers`): the document's fenced ```layers blocks. A line naming a source folder
starts a crate; each indented line under it is one layer, bottom first, listing module paths
(`io`, `pipelines::nvs`); a module belongs to the layer of its longest listed prefix, and may use
modules of its own layer and those below, never one above. A module that belongs to no layer is
refused, except a folder's `mod.rs` that only declares and re-exports listed children. A line
`CRATE_SRC uses CRATE: PATH...` lists the only paths into another workspace crate its code may name
(`uses datagen: io::sequence pairs`); `uses CRATE: -` forbids that crate. With `--workspace`, every
member crate of the workspace manifest is checked and each must have a block (a crate without one
is refused), so a new crate cannot slip past the rules.

A module is a source file (`a/b.rs` or `a/b/mod.rs` is module `a::b`; `lib.rs` and `main.rs` are
the crate root). Module A depends on module B when A's code (comments and tests excluded) names a
path into B: `crate::b::...`, `super::...`, or `self::...`, resolved to the deepest module the
path reaches. A path that stops at a module's re-export (`pub use child::Item;` in a `mod.rs`) is
followed to the child that defines the item, so siblings that use each other through their
parent's re-exports are seen as what they are. A parent declaring or re-exporting its children is
containment, not use, and is not an edge. Every strongly connected group of more than one module
is a cycle.
"""

import re
import sys
from pathlib import Path

PATH = re.compile(r"\b(crate|super|self)((?:::[A-Za-z_][A-Za-z0-9_]*)+|::\{)")
USE_GROUP = re.compile(r"\buse\s+((?:crate|super|self)(?:::[A-Za-z_][A-Za-z0-9_]*)*)::\{([^;]*)\};", re.S)
REEXPORT = re.compile(r"\bpub(?:\([a-z]+\))?\s+use\s+([a-z_][a-z0-9_]*)::(\{[^;]*\}|[A-Za-z_][A-Za-z0-9_]*(?:\s+as\s+\w+)?);", re.S)


# Comments, string and character literals and lifetimes, matched left to right in one pass, so
# that a `//` inside a string, a `"` character literal or a string continued over lines with a
# trailing backslash cannot make the rest of a file look like a string (hiding its paths).
TOKEN = re.compile(
    r"//[^\n]*|/\*.*?\*/"  # comments
    r'|b?r(#*)".*?"\1'  # raw strings
    r'|b?"(?:\\.|[^"\\])*"'  # strings (`.` spans lines: a backslash may end one)
    r"|b?'(?:\\.|[^'\\\n])'"  # character literals
    r"|'[A-Za-z_]\w*",  # lifetimes and labels, which have no closing quote
    re.S,
)


def strip(text: str) -> str:
    """The code without comments, string literals and `#[cfg(test)]` modules."""
    def blank(token: re.Match) -> str:
        kind = token.group(0)
        if kind.startswith("/"):
            return ""
        return "''" if kind.lstrip("b").startswith("'") and kind.endswith("'") else '""' if '"' in kind else kind

    text = TOKEN.sub(blank, text)
    start = text.find("#[cfg(test)]")
    return text if start < 0 else text[:start]


def modules(src: Path) -> dict[tuple[str, ...], Path]:
    found = {}
    for path in src.rglob("*.rs"):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "mod":
            parts.pop()
        if parts in (["lib"], ["main"]) or (parts and parts[0] in ("bin",)):
            parts = []
        found.setdefault(tuple(parts), path)
    return found


def reexports(code: str) -> dict[str, str]:
    """Item name -> child module, from a module's `pub use child::...;` lines."""
    items = {}
    for child, body in REEXPORT.findall(code):
        for item in re.findall(r"[A-Za-z_][A-Za-z0-9_]*(?:\s+as\s+[A-Za-z_]\w*)?", body.strip("{}")):
            name = item.split(" as ")[-1].strip()
            items[name] = child
    return items


def resolve(path: list[str], mods: dict, exports: dict) -> tuple[str, ...] | None:
    """The deepest module `path` (absolute segments) reaches, following re-exports one level."""
    best = None
    for i in range(len(path) + 1):
        head = tuple(path[:i])
        if head in mods:
            best = head
            if i < len(path) and path[i] in exports.get(head, {}):
                child = head + (exports[head][path[i]],)
                if child in mods:
                    return child
        elif i > 0:
            break
    return best


def edges_of(module: tuple[str, ...], code: str, mods: dict, exports: dict) -> set[tuple[str, ...]]:
    here = list(module) if mods[module].name in ("mod.rs", "lib.rs", "main.rs") else list(module)
    parent = list(module[:-1])

    def absolute(root: str, rest: list[str]) -> list[str]:
        return {"crate": [], "super": parent, "self": here}[root] + rest

    targets = set()
    for prefix, body in USE_GROUP.findall(code):
        segments = prefix.split("::")
        base = absolute(segments[0], segments[1:])
        for item in re.findall(r"[A-Za-z_][A-Za-z0-9_:]*", body):
            if item in ("self", "as"):
                continue
            target = resolve(base + item.split("::"), mods, exports)
            if target is not None:
                targets.add(target)
    for root, rest in PATH.findall(code):
        if rest == "::{":
            continue
        target = resolve(absolute(root, rest.strip(":").split("::")), mods, exports)
        if target is not None:
            targets.add(target)
    # A module using its own items, or a parent its children, is not a dependency.
    return {t for t in targets if t != module and t[: len(module)] != module}


def cycles(graph: dict) -> list[list]:
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    sys.setrecursionlimit(10_000)
    for v in graph:
        if v not in index:
            visit(v)
    return out


def check(src: Path) -> list[str]:
    mods = modules(src)
    codes = {m: strip(p.read_text()) for m, p in mods.items()}
    exports = {m: reexports(c) for m, c in codes.items()}
    graph = {m: edges_of(m, c, mods, exports) for m, c in codes.items()}
    problems = []
    for group in cycles(graph):
        names = ["::".join(m) or "crate" for m in group]
        uses = [f"{'::'.join(a) or 'crate'} -> {'::'.join(b) or 'crate'}" for a in group for b in graph[a] if b in group]
        problems.append(f"{src}: import cycle among {', '.join(names)} ({'; '.join(uses)})")
    return problems


def graph_of(src: Path) -> dict:
    mods = modules(src)
    codes = {m: strip(p.read_text()) for m, p in mods.items()}
    exports = {m: reexports(c) for m, c in codes.items()}
    return {m: edges_of(m, c, mods, exports) for m, c in codes.items()}, codes


def read_layers(doc: Path) -> tuple[dict, dict]:
    """({crate src: [layer, ...] with each layer a list of module paths}, {(crate src, other
    crate): allowed paths or []}) from the ```layers blocks of `doc`."""
    layers, uses = {}, {}
    for block in re.findall(r"```layers\n(.*?)```", doc.read_text(), re.S):
        crate = None
        for line in block.splitlines():
            text = line.split("#")[0].rstrip()
            if not text.strip():
                continue
            if m := re.match(r"(\S+) uses (\w+):\s*(.*)$", text.strip()):
                paths = m.group(3).split()
                uses[(m.group(1), m.group(2))] = [] if paths == ["-"] else paths
            elif not text.startswith((" ", "\t")):
                crate = text.strip()
                layers[crate] = []
            elif crate is not None:
                layers[crate].append(text.split())
    return layers, uses


def layer_of(module: tuple[str, ...], layers: list) -> int | None:
    best, depth = None, -1
    for level, names in enumerate(layers):
        for name in names:
            parts = tuple(name.split("::"))
            if module[: len(parts)] == parts and len(parts) > depth:
                best, depth = level, len(parts)
    return best


def check_layers(src: Path, key: str, layers: list, uses: dict) -> list[str]:
    graph, codes = graph_of(src)
    problems = []
    for module, targets in sorted(graph.items()):
        own = layer_of(module, layers)
        if own is None:
            # The crate root, and a folder's `mod.rs` that only declares or re-exports its children
            # (containment, no edges of its own), are not modules of any one layer.
            container = not targets and any(m[: len(module)] == module and m != module for m in graph)
            if module and not container:
                problems.append(f"{src}: {'::'.join(module)} belongs to no layer of the document's block for {key}")
            continue
        for target in sorted(targets):
            other = layer_of(target, layers)
            if other is not None and other > own:
                problems.append(
                    f"{src}: {'::'.join(module)} (layer {own}: {' '.join(layers[own])}) uses "
                    f"{'::'.join(target)} (layer {other}: {' '.join(layers[other])}), a higher layer"
                )
    for (crate, other), allowed in uses.items():
        if crate != key:
            continue
        for module, code in sorted(codes.items()):
            for path in sorted(crate_paths(code, other)):
                parts = path.strip(":").split("::") if path else []
                if not any(parts[: len(a.split("::"))] == a.split("::") for a in allowed):
                    problems.append(
                        f"{src}: {'::'.join(module) or 'crate'} names {other}{path}, outside what it may use of "
                        f"{other} ({' '.join(allowed) or 'nothing'})"
                    )
    return problems


def group_items(group: str) -> list[str]:
    """The top-level items of a `use` group's inside (`a, b::{c, d}, e as f`), nesting kept."""
    items, depth, start = [], 0, 0
    for i, ch in enumerate(group):
        depth += {"{": 1, "}": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            items.append(group[start:i])
            start = i + 1
    items.append(group[start:])
    return [item.strip() for item in items if item.strip()]


def expand_group(prefix: str, group: str) -> set[str]:
    """Every path a `use` group names: `x::{a, b::{c, self}, d as e, *}` under `x` is `x::a`,
    `x::b::c`, `x::b`, `x::d` and `x` (a glob names what its prefix holds)."""
    paths = set()
    for item in group_items(group):
        item = re.sub(r"\s+as\s+\w+$", "", item)
        if m := re.fullmatch(r"((?:[A-Za-z_]\w*::)*)\{(.*)\}", item, re.S):
            paths |= expand_group(prefix + "::" + m.group(1).rstrip(":") if m.group(1) else prefix, m.group(2))
        elif item in ("self", "*"):
            paths.add(prefix)
        else:
            paths.add(f"{prefix}::{item}")
    return {p.replace("::::", "::") for p in paths}


def crate_paths(code: str, other: str) -> set[str]:
    """Every path into crate `other` that `code` names, as `::a::b` (`""` for the bare crate, as
    `use other;` or `use other as alias;` name it): plain paths, and each path of a `use` group
    (`other::{a::b, c}`), so that a group cannot hide a path from the allowed list."""
    paths = set()
    for m in re.finditer(rf"\b{other}\b((?:\s*::\s*[A-Za-z_][A-Za-z0-9_]*)*)(\s*::\s*\{{)?", code):
        prefix = re.sub(r"\s+", "", m.group(1))
        if not m.group(2):
            paths.add(prefix)
            continue
        depth, end = 1, m.end()
        while end < len(code) and depth:
            depth += {"{": 1, "}": -1}.get(code[end], 0)
            end += 1
        paths |= {p[len(other):] for p in expand_group(other + prefix, code[m.end() : end - 1])}
    return paths


def workspace_members(manifest: Path) -> list[str]:
    """The `src` folders of a Cargo workspace manifest's `[workspace] members`, relative to the
    current folder as the manifest's folder is."""
    import tomllib
    members = tomllib.loads(manifest.read_text()).get("workspace", {}).get("members", [])
    base = manifest.parent
    return [str(Path(base, m, "src")) if str(base) != "." else f"{m}/src" for m in members]


def self_test() -> None:
    """A cycle through a parent's re-export, a direct one, one after string and character literals
    that fooled a line-by-line stripper, and a one-way use: the first three found, the last not."""
    import tempfile
    crates = {
        "reexport": {"lib.rs": "pub mod a;\npub mod b;", "a/mod.rs": "mod x;\npub use x::Thing;",
                     "a/x.rs": "use crate::b::helper;\npub struct Thing;", "b.rs": "use crate::a::Thing;\npub fn helper() {}"},
        "direct": {"lib.rs": "mod a;\nmod b;", "a.rs": "fn f() { crate::b::g() }", "b.rs": "use super::a;"},
        "literals": {"lib.rs": "mod a;\nmod b;", "b.rs": "use super::a;",
                     "a.rs": "fn f() { let s = \"x \\\n y\"; crate::b::g(); let q = '\"'; let l: &'static str = \"//\"; }"},
        "acyclic": {"lib.rs": "mod a;\nmod b;", "a.rs": "use crate::b::g;", "b.rs": "// crate::a::f in a comment\n"
                    "#[cfg(test)]\nmod tests { use crate::a::f; }"},
    }
    with tempfile.TemporaryDirectory() as root:
        found = {}
        for name, files in crates.items():
            for rel, text in files.items():
                path = Path(root, name, rel)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(text)
            found[name] = check(Path(root, name))
    assert found["reexport"] and "a::x" in found["reexport"][0] and " b" in found["reexport"][0], found
    assert found["direct"], found
    assert found["literals"], found
    assert not found["acyclic"], found
    with tempfile.TemporaryDirectory() as root:
        files = {"lib.rs": "pub mod low;\npub mod high;", "low/mod.rs": "pub mod a;", "low/a.rs": "use crate::high::b;",
                 "high/mod.rs": "pub mod b;", "high/b.rs": "fn f() { other::inner::x(); other::api::y(); }",
                 "high/c.rs": "use other::{api::{self, z}, grouped::{w as v}};\nuse other as alias;"}
        for rel, text in files.items():
            path = Path(root, "c", rel)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        doc = Path(root, "doc.md")
        Path(root, "c", "stray.rs").write_text("use crate::low::a;")
        Path(root, "c", "lib.rs").write_text("pub mod low;\npub mod high;\npub mod stray;")
        Path(root, "c", "high", "mod.rs").write_text("pub mod b;\npub mod c;")
        doc.write_text("```layers\nc\n  low\n  high\nc uses other: api\n```\n")
        layers, uses = read_layers(doc)
        problems = check_layers(Path(root, "c"), "c", layers["c"], uses)
    assert any("low::a" in p and "higher layer" in p for p in problems), problems
    assert any("other::inner::x" in p for p in problems) and not any("other::api" in p for p in problems), problems
    # A path inside a `use` group, and the bare crate under an alias, are refused as plain paths are.
    assert any("names other::grouped::w," in p for p in problems), problems
    assert any("high::c names other," in p for p in problems), problems
    assert any("stray belongs to no layer" in p for p in problems), problems
    assert not any(p.split(": ")[1].startswith(("low belongs", "high belongs")) for p in problems), problems
    print("self-test: cycles through re-exports, direct ones and ones after literals found, none where there is none;"
          " a use of a higher layer, a module in no layer and a path outside another crate's allowed API found")


def main() -> None:
    args = sys.argv[1:]
    if not args or any(a in ("-h", "--help") for a in args):
        print(__doc__.strip())
        sys.exit(0 if args else 2)
    if args == ["--self-test"]:
        self_test()
        return
    layers, uses = {}, {}
    if args[:1] == ["--layers"]:
        if len(args) < 2 or not Path(args[1]).is_file():
            print("check_module_cycles.py: --layers needs a document (see --help)", file=sys.stderr)
            sys.exit(2)
        layers, uses = read_layers(Path(args[1]))
        args = args[2:]
    if args[:1] == ["--workspace"]:
        if len(args) != 2 or not Path(args[1]).is_file() or not layers:
            print("check_module_cycles.py: --workspace needs --layers first and a Cargo.toml (see --help)", file=sys.stderr)
            sys.exit(2)
        args = workspace_members(Path(args[1]))
        without = [a for a in args if a not in layers]
        if without:
            print(f"check_module_cycles.py: no ```layers block for {', '.join(without)}: every workspace crate needs one",
                  file=sys.stderr)
            sys.exit(1)
    unknown = [a for a in args if a.startswith("-")]
    missing = [a for a in args if not a.startswith("-") and not Path(a).is_dir()]
    if unknown or missing:
        print(f"check_module_cycles.py: {'unknown option ' + unknown[0] if unknown else 'no such folder ' + missing[0]}"
              " (see --help)", file=sys.stderr)
        sys.exit(2)
    problems = [p for arg in args for p in check(Path(arg))]
    for arg in args:
        key = arg.rstrip("/")
        if key in layers:
            problems += check_layers(Path(arg), key, layers[key], uses)
    for p in problems:
        print(p)
    if problems:
        sys.exit(1)
    checked = [a for a in args if a.rstrip("/") in layers]
    print(f"no import cycles in {', '.join(args)}" + (f"; layer rules hold in {', '.join(checked)}" if checked else ""))


if __name__ == "__main__":
    main()
