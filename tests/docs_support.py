"""Reading the documentation for tests/test_docs.py: fenced code blocks with their
`<!-- docs-test: ... -->` annotations, relative links and their anchors, and the Python names
the pages mention."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the pages whose code blocks run: the front door and the topic pages
BLOCK_PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# the pages whose links must resolve
LINK_PAGES = [*BLOCK_PAGES, ROOT / "BENCHMARKS.md"]

ANNOTATION = re.compile(r"^\s*<!--\s*docs-test:(?P<body>.*?)-->\s*$")
FENCE = re.compile(r"^(?P<indent>\s{0,3})(?P<fence>`{3,}|~{3,})(?P<info>.*)$")
# annotation words; `needs=a,b` names the inputs the test creates before the block runs
TAGS = {
    "realdata": "needs ../shared/data and takes minutes: runs with SLAMRELOC_DOCS_REALDATA=1",
    "slow": "takes minutes on the synthetic scene: runs with SLAMRELOC_DOCS_SLOW=1",
    "server": "starts a long-running server: started, asked whether it answers, stopped",
    "make-dry-run": "make targets: each line's target is checked with `make -n`",
    "pyproject": "an excerpt of pyproject.toml: checked against it, entry points loaded",
    "output": "sample output of a command, not a command",
    "network": "downloads from the internet",
    "cluster": "needs a Ray cluster of several machines",
}


@dataclass
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    tags: set[str] = field(default_factory=set)
    needs: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def id(self) -> str:
        return f"{self.page.relative_to(ROOT).as_posix()}:{self.line}"


def parse_annotation(line: str) -> tuple[set[str], list[str], list[str]] | None:
    """(tags, needs, problems) of an annotation line, None when the line is not one."""
    m = ANNOTATION.match(line)
    if m is None:
        return None
    tags, needs, problems = set(), [], []
    for word in m.group("body").split():
        if word.startswith("needs="):
            needs += [n for n in word[len("needs="):].split(",") if n]
        elif word in TAGS:
            tags.add(word)
        else:
            problems.append(f"unknown docs-test annotation word '{word}' (known: "
                            f"{', '.join(sorted(TAGS))}, needs=...)")
    return tags, needs, problems


def code_blocks(page: Path) -> list[Block]:
    """Every fenced block of a page, with the annotation on the line directly above it."""
    lines = page.read_text().split("\n")
    blocks, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m is None:
            i += 1
            continue
        fence, start = m.group("fence"), i
        lang = m.group("info").strip().split()[0].lower() if m.group("info").strip() else ""
        closing = re.compile(rf"^\s{{0,3}}{re.escape(fence[0])}{{{len(fence)},}}\s*$")
        j = i + 1
        while j < len(lines) and not closing.match(lines[j]):
            j += 1
        block = Block(page, start + 1, lang, "\n".join(lines[start + 1:j]) + "\n")
        if j == len(lines):
            block.problems.append("the block is never closed")
        above = parse_annotation(lines[start - 1]) if start > 0 else None
        if above is not None:
            block.tags, block.needs, block.problems = above[0], above[1], \
                block.problems + above[2]
        blocks.append(block)
        i = j + 1
    return blocks


def all_blocks() -> list[Block]:
    return [b for page in BLOCK_PAGES for b in code_blocks(page)]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, markup and punctuation dropped, spaces to -."""
    text = re.sub(r"`|\*\*|\*|_(?=\w)|(?<=\w)_", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    in_fence = False
    for line in page.read_text().split("\n"):
        if FENCE.match(line):
            in_fence = not in_fence
        if in_fence or not line.startswith("#"):
            continue
        base = slug(line.lstrip("#"))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


LINK = re.compile(r"(?<!!)\[[^\]]*\]\((?P<target>[^)\s]+)\)|!\[[^\]]*\]\((?P<image>[^)\s]+)\)")


def relative_links(page: Path) -> list[tuple[int, str]]:
    """(line, target) of every link and image that is not a URL, outside code blocks."""
    out, in_fence = [], False
    for n, line in enumerate(page.read_text().split("\n"), 1):
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        if in_fence or line.startswith("    "):
            continue
        for m in LINK.finditer(re.sub(r"`[^`]*`", "", line)):
            target = m.group("target") or m.group("image")
            if not re.match(r"^[a-z]+:", target):
                out.append((n, target))
    return out


# `slamreloc.x.y` in backticks (a module, or a module's attribute) and `slamreloc/...`,
# `plugins/...` paths of the source tree
DOTTED = re.compile(r"`(slamreloc(?:\.[A-Za-z_][A-Za-z0-9_]*)+)")
SOURCE_PATH = re.compile(r"`((?:slamreloc|plugins|pseudo_label|viewer|tests|benchmarks|scripts|"
                         r"clients|deploy)/[\w./-]*)`")
# scripts a page tells to run: `python benchmarks/x.py`, `python -m benchmarks.x`
SCRIPT_RUN = re.compile(r"python3? (?:-m )?((?:benchmarks|scripts)[./][\w./]*\w)")


def script_file(name: str) -> Path:
    """The file `python NAME` or `python -m NAME` runs."""
    return ROOT / (name if name.endswith(".py") else name.replace(".", "/") + ".py")

