"""Check a colcon install of soft_arm: every console script under lib/soft_arm, every parameter
file under share/soft_arm/config and every launch file under share/soft_arm/launch; and the packages
colcon found (``colcon list --topological-order``): soft_arm_interfaces, an ament_cmake package,
before soft_arm, which depends on it."""
import pathlib
import re
import sys

root = pathlib.Path(__file__).resolve().parents[1]
prefix, listed = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
scripts = re.findall(r'"([\w-]+) = [\w.]+:main"', (root / "setup.py").read_text())
expected = [prefix / "lib" / "soft_arm" / s for s in scripts]
expected += [prefix / "share" / "soft_arm" / "config" / p.name for p in (root / "config").glob("*.yaml")]
expected += [prefix / "share" / "soft_arm" / "launch" / p.name
             for p in (root / "launch").glob("*.launch.py")]
expected += [prefix / "share" / "soft_arm" / "package.xml"]
missing = [str(p) for p in expected if not p.is_file()]
if missing or not scripts:
    sys.exit("colcon install layout is missing:\n  " + "\n  ".join(missing or ["console scripts"]))
packages = [line.split("\t") for line in listed.read_text().splitlines()]
found = [(name, kind) for name, _, kind in packages]
if found != [("soft_arm_interfaces", "(ros.ament_cmake)"), ("soft_arm", "(ros.ament_python)")]:
    sys.exit(f"colcon should find soft_arm_interfaces (ament_cmake), then soft_arm; found {found}")
print(f"colcon install layout: {len(scripts)} executables, config and launch files in place; "
      "packages soft_arm_interfaces, soft_arm")
