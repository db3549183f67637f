"""Jobs: long runs over a store that write results back (teacher pairs, shadow maps, baseline comparisons)."""
