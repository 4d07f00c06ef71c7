"""Hardware drivers (real and fake) and the simulated world."""
