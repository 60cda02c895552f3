"""Check a colcon install of soft_arm: every console script under lib/soft_arm, every parameter
file under share/soft_arm/config and every launch file under share/soft_arm/launch."""
import pathlib
import re
import sys

root = pathlib.Path(__file__).resolve().parents[1]
prefix = pathlib.Path(sys.argv[1])
scripts = re.findall(r'"([\w-]+) = [\w.]+:main"', (root / "setup.py").read_text())
expected = [prefix / "lib" / "soft_arm" / s for s in scripts]
expected += [prefix / "share" / "soft_arm" / "config" / p.name for p in (root / "config").glob("*.yaml")]
expected += [prefix / "share" / "soft_arm" / "launch" / p.name
             for p in (root / "launch").glob("*.launch.py")]
expected += [prefix / "share" / "soft_arm" / "package.xml"]
missing = [str(p) for p in expected if not p.is_file()]
if missing or not scripts:
    sys.exit("colcon install layout is missing:\n  " + "\n  ".join(missing or ["console scripts"]))
print(f"colcon install layout: {len(scripts)} executables, config and launch files in place")
