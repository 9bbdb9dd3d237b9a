"""What the benchmark scripts share in writing their reports."""

import json


def write_markdown(path, lines, meta) -> str:
    """The table ``lines`` and the run's ``meta`` (as one JSON line) into ``path``; printed too."""
    text = "\n".join(lines) + f"\n\n{json.dumps(meta)}\n"
    with open(path, "w") as f:
        f.write(text)
    print(text)
    return text
