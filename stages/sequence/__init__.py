"""Stage ``sequence``: OLAT order, capture pattern, frame schedule and controller program."""
