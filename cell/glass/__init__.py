"""Back-imaging inspection of specular glass."""
