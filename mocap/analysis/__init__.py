"""Dig-cycle analysis: cycles, phases, classes, similarity, templates, deviations, relations."""
