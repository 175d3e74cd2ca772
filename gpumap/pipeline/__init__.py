"""Drivers' library: one pipeline feeds pings from recordings to a mapper and its layers."""
