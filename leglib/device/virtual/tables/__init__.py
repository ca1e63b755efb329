"""The ODrive firmware's endpoint tables (package data); see README.md here."""
