"""Results used: pictures (`render`), relighting, held-out-light validation, PLY export."""
