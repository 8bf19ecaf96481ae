/*
 * notify.c - completion notifications on a thread of their own (notify.h).
 */
#include "notify.h"

#include <curl/curl.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct delivery {
    char *url, *body;
    int attempts;        /* made so far */
    double due;          /* mr_now() of the next attempt */
    struct delivery *next;
} delivery;

struct mr_notifier {
    pthread_mutex_t mu;
    pthread_cond_t cv;
    pthread_t thread;
    bool stop;
    delivery *queue;     /* by due time */
    void (*log)(void *user, const char *line);
    void *log_user;
};

static void say(mr_notifier *n, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static void say(mr_notifier *n, const char *fmt, ...)
{
    if (!n->log)
        return;
    char line[1024];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(line, sizeof line, fmt, ap);
    va_end(ap);
    n->log(n->log_user, line);
}

static void delivery_free(delivery *d)
{
    if (!d)
        return;
    free(d->url);
    free(d->body);
    free(d);
}

/* Inserts d by due time (n->mu held). */
static void enqueue(mr_notifier *n, delivery *d)
{
    delivery **p = &n->queue;
    while (*p && (*p)->due <= d->due)
        p = &(*p)->next;
    d->next = *p;
    *p = d;
}

static size_t discard(char *p, size_t size, size_t count, void *user)
{
    (void)p, (void)user;
    return size * count;
}

/* One attempt: the HTTP status, or 0 when no answer came (why in err). */
static long attempt(const delivery *d, char *err, size_t err_size)
{
    err[0] = '\0';
    CURL *c = curl_easy_init();
    if (!c) {
        snprintf(err, err_size, "cannot create a libcurl handle");
        return 0;
    }
    char attempt_header[64], agent[64], errbuf[CURL_ERROR_SIZE] = "";
    snprintf(attempt_header, sizeof attempt_header, "X-Microray-Attempt: %d", d->attempts + 1);
    snprintf(agent, sizeof agent, "microrayd/%s", MR_VERSION_STRING);
    struct curl_slist *h = curl_slist_append(NULL, "Content-Type: application/json");
    struct curl_slist *h2 = h ? curl_slist_append(h, attempt_header) : NULL;
    struct curl_slist *h3 = h2 ? curl_slist_append(h2, "Expect:") : NULL;
    long status = 0;
    if (!h3) {
        snprintf(err, err_size, "out of memory");
        curl_slist_free_all(h2 ? h2 : h);
        curl_easy_cleanup(c);
        return 0;
    }
    curl_easy_setopt(c, CURLOPT_URL, d->url);
    curl_easy_setopt(c, CURLOPT_PROTOCOLS_STR, "http,https");
    curl_easy_setopt(c, CURLOPT_FOLLOWLOCATION, 0L);
    curl_easy_setopt(c, CURLOPT_NOSIGNAL, 1L);
    curl_easy_setopt(c, CURLOPT_CONNECTTIMEOUT, 5L);
    curl_easy_setopt(c, CURLOPT_TIMEOUT, (long)NOTIFY_TIMEOUT_S);
    curl_easy_setopt(c, CURLOPT_USERAGENT, agent);
    curl_easy_setopt(c, CURLOPT_HTTPHEADER, h3);
    curl_easy_setopt(c, CURLOPT_POSTFIELDS, d->body);
    curl_easy_setopt(c, CURLOPT_POSTFIELDSIZE, (long)strlen(d->body));
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, discard);
    curl_easy_setopt(c, CURLOPT_ERRORBUFFER, errbuf);
    CURLcode rc = curl_easy_perform(c);
    if (rc == CURLE_OK)
        curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &status);
    else
        snprintf(err, err_size, "%s", errbuf[0] ? errbuf : curl_easy_strerror(rc));
    curl_slist_free_all(h3);
    curl_easy_cleanup(c);
    return status;
}

static void *notifier_main(void *arg)
{
    mr_notifier *n = arg;
    pthread_mutex_lock(&n->mu);
    while (!n->stop) {
        if (!n->queue) {
            pthread_cond_wait(&n->cv, &n->mu);
            continue;
        }
        double now = mr_now();
        if (n->queue->due > now) {
            struct timespec ts;
            clock_gettime(CLOCK_MONOTONIC, &ts);
            double wait = n->queue->due - now;
            ts.tv_sec += (time_t)wait;
            ts.tv_nsec += (long)((wait - (double)(time_t)wait) * 1e9);
            if (ts.tv_nsec >= 1000000000L) {
                ts.tv_sec++;
                ts.tv_nsec -= 1000000000L;
            }
            pthread_cond_timedwait(&n->cv, &n->mu, &ts);
            continue;
        }
        delivery *d = n->queue;
        n->queue = d->next;
        pthread_mutex_unlock(&n->mu);
        char why[CURL_ERROR_SIZE + 32];
        long status = attempt(d, why, sizeof why);
        d->attempts++;
        bool ok = status >= 200 && status < 300;
        if (!ok && status)
            snprintf(why, sizeof why, "answered %ld", status);
        pthread_mutex_lock(&n->mu);
        if (ok) {
            if (d->attempts > 1)
                say(n, "notify %s: delivered at attempt %d", d->url, d->attempts);
            delivery_free(d);
        } else if (d->attempts >= NOTIFY_ATTEMPTS) {
            say(n, "notify %s: given up after %d attempts (%s)", d->url, d->attempts, why);
            delivery_free(d);
        } else {
            /* 1, 2, 4, 8, 16 s */
            d->due = mr_now() + (double)(1 << (d->attempts - 1));
            enqueue(n, d);
        }
    }
    size_t dropped = 0;
    for (delivery *d = n->queue, *next; d; d = next) {
        next = d->next;
        delivery_free(d);
        dropped++;
    }
    n->queue = NULL;
    if (dropped)
        say(n, "notify: %zu pending deliver%s dropped at stop", dropped, dropped == 1 ? "y" : "ies");
    pthread_mutex_unlock(&n->mu);
    return NULL;
}

int mr_notifier_start(void (*log)(void *user, const char *line), void *user, mr_notifier **out,
                      mr_error *err)
{
    *out = NULL;
    mr_notifier *n = calloc(1, sizeof *n);
    if (!n)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    n->log = log;
    n->log_user = user;
    pthread_condattr_t ca;
    pthread_condattr_init(&ca);
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    bool ok = pthread_mutex_init(&n->mu, NULL) == 0 && pthread_cond_init(&n->cv, &ca) == 0;
    pthread_condattr_destroy(&ca);
    if (!ok || pthread_create(&n->thread, NULL, notifier_main, n) != 0) {
        free(n);
        return mr_error_set(err, MR_ERR_NOMEM, "cannot start the notification thread");
    }
    *out = n;
    return MR_OK;
}

void mr_notifier_send(mr_notifier *n, const char *url, const char *body)
{
    if (!n || !url || !body)
        return;
    delivery *d = calloc(1, sizeof *d);
    if (d) {
        d->url = strdup(url);
        d->body = strdup(body);
    }
    if (!d || !d->url || !d->body) {
        delivery_free(d);
        say(n, "notify %s: out of memory, not sent", url);
        return;
    }
    d->due = mr_now();
    pthread_mutex_lock(&n->mu);
    enqueue(n, d);
    pthread_cond_signal(&n->cv);
    pthread_mutex_unlock(&n->mu);
}

void mr_notifier_stop(mr_notifier *n)
{
    if (!n)
        return;
    pthread_mutex_lock(&n->mu);
    n->stop = true;
    pthread_cond_signal(&n->cv);
    pthread_mutex_unlock(&n->mu);
    pthread_join(n->thread, NULL);
    pthread_cond_destroy(&n->cv);
    pthread_mutex_destroy(&n->mu);
    free(n);
}
