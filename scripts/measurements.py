"""Per-run records of the studies, kept as one compressed archive per study (studies/records.py).

    python scripts/measurements.py pack STUDY [STUDY ...] | --all   # folders -> STUDY/records.tar.xz
    python scripts/measurements.py extract STUDY [--dest DIR]       # records.tar.xz -> the folders again
    python scripts/measurements.py list                              # what each study keeps and archives
"""
import sys
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, whose studies/ package this runs
    from studies.records import main
    main()
