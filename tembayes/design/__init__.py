"""Designing an identification run before rig time is spent (``tembayes design``, ``docs/design.md``).

:mod:`.protocol` reads and writes ``protocol.csv``; :mod:`.widths` gives the
laws' expected posterior sds on a run; :mod:`.search` finds the shortest
staircase that reaches target sds.
"""
