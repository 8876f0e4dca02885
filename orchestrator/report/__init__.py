"""What a user reads: the run's HTML report and its figures (`run_report`, `figures`), the model as ParaView files (`paraview`) and the report of a study (`study_report`)."""
