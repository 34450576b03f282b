"""What users do with a result file: simulate, batch runs and their report, plots, the
summary, exports to other tools. Nothing here imports the FE stack."""
