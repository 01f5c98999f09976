"""Tests of the ground-floor lab-data definitions."""
