"""calfit design: from an identified leg to the garment it needs, against the compression standards. One job a
module: the targets of TARGET.toml (`targets.py`), the standards' classes (`standards.py`), the identified slices and
what a garment gives on them through the FE model (`slices.py`), Levenberg-Marquardt on the garment (`solve.py`),
the probabilities over the Monte-Carlo draws and the tension's uncertainty (`uncertainty.py`), Laplace's law beside
it (`laplace.py`), the stage that writes design.json (`stage.py`), its figures and page (`report.py`)."""
