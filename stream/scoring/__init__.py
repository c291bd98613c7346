"""Scoring against ground truth: the replay fixtures' format and truth (:mod:`.fixture`), the metrics (SI-SDR,
STOI, SAR, SSARA, TOA error: :mod:`.metrics`), a run scored against its fixture (:mod:`.evaluate`) and the plots
of a run (:mod:`.plots`). The stream runs without it except for replays of fixtures and the plots."""
