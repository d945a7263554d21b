"""Reporting: the tables, figures, verdict and READMEs written from evaluation results (roboshape/eval/ evaluates,
this package reports; roboshape/eval/ writes each run's own summary through it)."""
