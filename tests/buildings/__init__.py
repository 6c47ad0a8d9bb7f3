"""Tests of the buildings stage (a package, so test module names do not clash across folders)."""
