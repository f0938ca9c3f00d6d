"""Jobs behind the top-level scripts (``evaluate.py``); the scripts only compose configs."""
