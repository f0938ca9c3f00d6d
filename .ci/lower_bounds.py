"""Print the lowest versions pyproject.toml allows, one ``name==version`` a line.

``.ci/run`` installs flowins against them (``pip install -c``) to prove that the
declared lower bounds are versions the test suite passes on. Every dependency
must carry a ``>=`` bound; a dependency without one is an error.
"""
import re
import sys
import tomllib
from pathlib import Path

project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
requirements = list(project["dependencies"])
for extra in project.get("optional-dependencies", {}).values():
    requirements += extra
for requirement in requirements:
    match = re.fullmatch(r"\s*([A-Za-z0-9_.\-]+)\s*>=\s*([0-9][0-9A-Za-z.+]*)\s*(,.*)?", requirement)
    if match is None:
        sys.exit(f"pyproject.toml: dependency {requirement!r} has no '>=' lower bound")
    print(f"{match[1]}=={match[2]}")
