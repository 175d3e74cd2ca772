"""Experiments: measurements of mechanisms not (yet) in the library's default path (DESIGN.md: a
mechanism stays only while a benchmark row shows it winning; its experiment lives here)."""
