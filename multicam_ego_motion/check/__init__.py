"""`ego-motion check SUITE.yaml`: regression suites of bags, replayed and judged.

suite.py reads and validates the suite file, bags.py generates the bags a suite describes by
scenario (into a cache), figures.py scores a run and compares it with limits and a baseline,
baseline.py reads and writes baseline files, report.py writes the table, summary.md,
junit.xml and results.json, command.py is the command that ties them together.
"""
