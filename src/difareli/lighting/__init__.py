"""Light: the SH basis and its operations, the skin albedo prior, a record's SH light fit."""
