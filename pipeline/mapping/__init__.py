"""Map building from laser scans with known poses."""
