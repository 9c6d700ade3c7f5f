"""The bottom band: constants, errors, configuration dataclasses, typed command lines and the
small torch helpers that every other part of tbsim builds on. Imports nothing of tbsim above."""
