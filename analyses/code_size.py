"""Size of the package's functions and files in statements (independent of line formatting).

usage: python analyses/code_size.py [PACKAGE_DIR] [N]

Prints the N largest functions (statements, nested functions counted in their
parent), how many exceed 40 and 60 statements, and the largest files.
"""

import ast
import sys
from pathlib import Path


def _statements(node):
    return sum(isinstance(x, ast.stmt) for x in ast.walk(node))


PACKAGE = Path(__file__).resolve().parents[1] / "tembayes"


def main(root=PACKAGE, n=12):
    root = Path(root)
    functions, files = [], []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text())
        name = path.relative_to(root.parent)
        files.append((_statements(tree), f"{name}"))
        for f in ast.walk(tree):
            if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)):
                functions.append((_statements(f) - 1, f"{name}:{f.name}"))
    functions.sort(reverse=True)
    files.sort(reverse=True)
    print("largest functions (statements):")
    for size, where in functions[:n]:
        print(f"  {size:4d}  {where}")
    over60 = sum(s > 60 for s, _ in functions)
    over40 = sum(s > 40 for s, _ in functions)
    print(f"functions: {len(functions)}, over 60 statements: {over60}, over 40: {over40}")
    print("largest files (statements):")
    for size, where in files[:6]:
        print(f"  {size:4d}  {where}")


if __name__ == "__main__":
    main(*(sys.argv[1:2] or []), *(int(a) for a in sys.argv[2:3]))
