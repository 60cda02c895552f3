"""package.xml declares what setup.py requires, as rosdep keys, and every ROS interface package the
code imports: a colcon/rosdep user gets the same dependencies as a pip user."""
import ast
import pathlib
import re
import xml.etree.ElementTree as ET

ROOT = pathlib.Path(__file__).resolve().parents[1]
# PyPI requirement -> (package.xml tag, rosdep key), or None with the reason it has no key
ROSDEP = {
    "numpy": ("exec_depend", "python3-numpy"),
    "scipy": ("exec_depend", "python3-scipy"),
    "numba": ("exec_depend", "python3-numba"),
    "PyYAML": ("exec_depend", "python3-yaml"),
    "matplotlib": ("exec_depend", "python3-matplotlib"),
    "python-can": ("exec_depend", "python3-can"),
    "mcap": None,                                  # no rosdep key
    "ros-jazzy-rclpy": ("exec_depend", "rclpy"),
    "ros-jazzy-common-interfaces": None,           # the message packages, checked from the imports
    "ros-jazzy-rmw-fastrtps-cpp": None,            # the ROS installation's default RMW
    "pytest": ("test_depend", "python3-pytest"),
    "hypothesis": ("test_depend", "python3-hypothesis"),
    "flake8": ("test_depend", "python3-flake8"),
    "rosbags": None,                               # no rosdep key
    "dask": None,                                  # campaigns (soft-arm-campaign): no rosdep key for
    "bokeh": None,                                 # distributed; pip, on every worker machine too
    "pytest-xdist": None,                          # the suite's parallel runner (test/run): pip
    "sphinx": None,                                # the documentation's build (docs/): pip, with
    "myst-parser": None,                           # MyST and the theme, which have no rosdep key;
    "furo": None,                                  # rosdoc2 brings its own on a ROS build farm
    "pyelastica": None,                            # the model bench's comparison: pip, no rosdep key
    "foxglove-sdk": None,                          # the live view's server: pip, no rosdep key
    "websockets": None,                            # the live view's test client: pip
    "protobuf": ("test_depend", "python3-protobuf"),
    "threadpoolctl": None,                         # a campaign test's BLAS threads: pip
}
INTERFACE = re.compile(r"^(\w+_(?:msgs|srvs|interfaces))(?:\.|$)")
ROS_PYTHON = re.compile(r"^(launch_ros|launch|ament_index_python|rclpy)(?:\.|$)")


def _requirements() -> dict:
    """setup.py's install_requires and its test extra, names only: {name: kind}."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    kw = {k.arg: ast.literal_eval(k.value) for k in call.keywords
          if k.arg in ("install_requires", "extras_require")}
    name = re.compile(r"^[A-Za-z0-9_.\-]+")
    out = {name.match(r).group(0): "exec_depend" for r in kw["install_requires"]}
    out.update({name.match(r).group(0): "test_depend" for r in kw["extras_require"]["test"]})
    return out


def _manifest() -> dict:
    root = ET.parse(ROOT / "package.xml").getroot()
    return {tag: {e.text for e in root.findall(tag)} for tag in ("exec_depend", "test_depend")}


def test_every_requirement_of_setup_py_is_declared_or_says_why_not():
    manifest = _manifest()
    for requirement, kind in _requirements().items():
        assert requirement in ROSDEP, f"{requirement}: add its rosdep key to package.xml and to ROSDEP"
        if ROSDEP[requirement] is None:
            continue
        tag, key = ROSDEP[requirement]
        assert tag == kind, (requirement, tag, kind)
        assert key in manifest[tag], f"package.xml lacks <{tag}>{key}</{tag}> for {requirement}"


def test_every_python_key_of_package_xml_comes_from_a_requirement():
    requirements = _requirements()
    mapped = {v[1]: k for k, v in ROSDEP.items() if v is not None}
    for tag, keys in _manifest().items():
        for key in keys:
            if key.startswith("python3-"):
                assert key in mapped and mapped[key] in requirements, f"<{tag}>{key}: not in setup.py"


def test_every_interface_package_imported_is_an_exec_depend():
    imported = set()
    for path in list(ROOT.glob("soft_arm_*/**/*.py")) + list(ROOT.glob("launch/*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
            for n in names:
                m = INTERFACE.match(n) or ROS_PYTHON.match(n)
                if m:
                    imported.add(m.group(1))
    assert {"std_msgs", "rclpy", "launch_ros"} <= imported        # the scan sees the imports
    missing = imported - _manifest()["exec_depend"]
    assert not missing, f"imported but not an exec_depend of package.xml: {sorted(missing)}"


def test_the_interface_package_builds_every_message_with_its_dependencies():
    """soft_arm_interfaces: CMakeLists.txt generates exactly msg/*.msg, with DEPENDENCIES naming
    every package whose types the messages use, each a <depend> of its package.xml."""
    package = ROOT / "soft_arm_interfaces"
    cmake = (package / "CMakeLists.txt").read_text()
    call = re.search(r"rosidl_generate_interfaces\(\$\{PROJECT_NAME\}(.*?)\)", cmake, re.S).group(1)
    listed = set(re.findall(r'"(msg/\w+\.msg)"', call))
    assert listed == {f"msg/{p.name}" for p in (package / "msg").glob("*.msg")} and listed
    dependencies = set(call.split("DEPENDENCIES", 1)[1].split())
    used = {line.split()[0].split("/")[0] for p in (package / "msg").glob("*.msg")
            for line in p.read_text().splitlines() if "/" in line.split("#")[0].split(" ")[0]}
    assert used == dependencies == {"std_msgs"}
    root = ET.parse(package / "package.xml").getroot()
    assert root.findtext("name") == "soft_arm_interfaces"
    assert dependencies <= {e.text for e in root.findall("depend")}
    assert {e.text for e in root.findall("member_of_group")} == {"rosidl_interface_packages"}
    assert all(f"find_package({d} REQUIRED)" in cmake for d in dependencies)
