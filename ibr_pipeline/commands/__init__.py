"""The `ibr` commands beyond the stages, one module each (the CLI layer: they may import anything).

Each module defines `register(sub)`, which adds its subparsers and sets `func` (args -> exit code)
on them; it imports nothing heavy at module level, so `ibr --help` stays fast.
"""
