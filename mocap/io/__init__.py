"""Reading and writing the project's file formats: one module per format."""
