"""Shared pytest set-up: the repository root on sys.path so `configs` and `roboshape` import from any cwd."""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
