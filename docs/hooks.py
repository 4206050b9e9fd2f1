"""MkDocs hook: generate the configs reference (docs/reference/configs.md) from conf/.

Every YAML in the built-in ``conf/`` folder gets a section: its group, name, one-line
description (``cobelrun.config.describe``) and its text. Runs on every build, so the page never
goes stale; the generated file is not committed.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def configs_page() -> str:
    """The markdown of the configs reference."""
    import sys

    sys.path.insert(0, str(ROOT))
    from cobelrun.config import describe

    conf = ROOT / "conf"
    lines = [
        "# Configs reference",
        "",
        "Every built-in config in `conf/` (generated from the files at build time). Choose one",
        "with `GROUP=NAME` on the command line (`cobel run task=tmaze_extinction agent=mfec`);",
        "put your own in `./conf/GROUP/NAME.yaml` (searched first).",
        "",
    ]
    for group in sorted(p for p in conf.iterdir() if p.is_dir() and not p.name.startswith("_")):
        files = sorted(group.rglob("*.yaml"))
        if not files:
            continue
        lines += [f"## {group.name}", ""]
        for f in files:
            name = f.relative_to(group).with_suffix("").as_posix()
            lines += [f"### {group.name}={name}", "", describe(f) or "", ""]
            lines += ["```yaml", f.read_text().rstrip(), "```", ""]
    return "\n".join(lines) + "\n"


def on_pre_build(config, **kwargs) -> None:
    out = Path(config["docs_dir"]) / "reference" / "configs.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    text = configs_page()
    if not out.is_file() or out.read_text() != text:
        out.write_text(text)
