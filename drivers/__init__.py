"""Real hardware drivers, one module per device. Hardware libraries are imported lazily inside each."""
