"""Rendering: the scene corpus (`scenes`), the split integrator, Mitsuba variants, the render stage."""
