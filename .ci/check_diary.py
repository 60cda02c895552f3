"""The product speaks of the product: no file of the packages, the tests, the benchmarks, the docs or
the README speaks of the work's history (stops, sessions, issue numbers). History belongs in
CHANGELOG.md and docs/decisions/. Prints each offending line and exits 1; 0 when there is none.

    python .ci/check_diary.py
"""
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WHERE = ["soft_arm_model", "soft_arm_ros", "soft_arm_control", "soft_arm_drivers", "soft_arm_interfaces",
         "test", "bench", "launch", "docs", "README.md"]
SUFFIXES = {".py", ".md", ".yaml", ".txt", ".rst"}
DIARY = re.compile(r"\b(stops? [0-9]+|(this|earlier|the last|next|at) stop\b|sessions?\b|issues? #?[0-9]+"
                   r"|the issue's|this issue|the robust-control issue)", re.IGNORECASE)
# API names that contain the words: pytest's fixture scope, subprocess's new process group
API = re.compile(r"scope=\"session\"|start_new_session")
SKIP = {"_build", "generated", "__pycache__"}


def files():
    for name in WHERE:
        path = ROOT / name
        if path.is_file():
            yield path
            continue
        for f in sorted(path.rglob("*")):
            if f.is_file() and f.suffix in SUFFIXES and not SKIP & set(f.relative_to(ROOT).parts):
                yield f


def main() -> int:
    found = 0
    for path in files():
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if DIARY.search(API.sub("", line)):
                print(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
                found += 1
    if found:
        print(f"{found} lines speak of the work's history: say why the code is as it is today "
              "(history: CHANGELOG.md, docs/decisions/)", file=sys.stderr)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
