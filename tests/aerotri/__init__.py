"""Tests of the aerotri stage (a package, so test module names do not clash across folders)."""
