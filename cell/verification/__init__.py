"""Acceptance test and re-verification of the cell after VDI/VDE 2634 Parts 2 and 3: calibrated artefacts
(sphere, ball bar, plane), the guideline's figures (PF, PS, SD, F) and the procedures that measure them."""
