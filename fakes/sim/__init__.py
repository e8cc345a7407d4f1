"""The physically based scene simulator that the simulated devices share."""
