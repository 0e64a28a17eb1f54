"""Certificates for mutual TLS: a mission's CA and one certificate per part."""
