"""Pictures the tutorials draw, kept out of the tutorials' own code."""
