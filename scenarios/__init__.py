"""The named scenarios (one folder each), shipped as package data so `scenario list/run` works from an installed package."""
