"""Print the README's set-up commands, one a line, exactly as the README writes them.

A command is the one line of a fenced ``bash`` block that directly follows the marker
``<!-- .ci/run runs this command -->``. ``.ci/run`` runs what this prints, so CI runs what
a new user copies; finding no marked command is an error.
"""
import sys
from pathlib import Path

MARKER = "<!-- .ci/run runs this command -->"

lines = Path(sys.argv[1]).read_text().splitlines()
commands = []
for i, line in enumerate(lines):
    if line.strip() != MARKER:
        continue
    block = lines[i + 1 : i + 4]
    if len(block) < 3 or block[0].strip() != "```bash" or block[2].strip() != "```":
        sys.exit(f"{sys.argv[1]}: line {i + 2}: expected a one-line ```bash block after {MARKER}")
    commands.append(block[1].strip())
if not commands:
    sys.exit(f"{sys.argv[1]}: no command marked with {MARKER}")
print("\n".join(commands))
