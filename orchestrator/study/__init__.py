"""Many cases: a folder of case folders or a volume cut into slice cases (`volume_cases`), run as tasks on Dask (`cohort`)."""
