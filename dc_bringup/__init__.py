"""dc-bringup (launcher and lifecycle manager) and the dc command-line tool."""
