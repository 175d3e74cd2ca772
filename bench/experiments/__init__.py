"""Experiments: mechanisms that no benchmark row shows winning for a named kind of scene (kept runnable).

Only bench/ imports them; the library never does.
"""
