"""Test support: independent references the library is checked against."""
