/*
 * notify.c - completion notifications on a thread of their own (notify.h).
 *
 * The thread keeps every attempt in flight at once in one libcurl multi
 * handle: a receiver that never answers holds its own delivery for
 * NOTIFY_TIMEOUT_S, not everyone's (one at a time, three such jobs held a
 * healthy receiver's notification back by about 30 s).
 */
#include "notify.h"

#include <curl/curl.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Attempts in flight at most; more wait their turn in the queue. */
#define NOTIFY_IN_FLIGHT 64

typedef struct delivery {
    char *url, *body;
    int attempts;        /* made so far */
    double due;          /* mr_now() of the next attempt */
    struct delivery *next;
    /* the attempt in flight (the thread's) */
    CURL *easy;
    struct curl_slist *headers;
    char errbuf[CURL_ERROR_SIZE];
} delivery;

struct mr_notifier {
    pthread_mutex_t mu;
    pthread_t thread;
    bool stop;           /* (mu) */
    delivery *queue;     /* waiting, by due time (mu) */
    CURLM *multi;        /* the attempts in flight; woken by send and stop */
    size_t in_flight;    /* (the thread's) */
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

/* Puts d's next attempt in flight; false (why in err) when it cannot. */
static bool attempt_start(mr_notifier *n, delivery *d, char *err, size_t err_size)
{
    char attempt_header[64], agent[64];
    snprintf(attempt_header, sizeof attempt_header, "X-Microray-Attempt: %d", d->attempts + 1);
    snprintf(agent, sizeof agent, "microrayd/%s", MR_VERSION_STRING);
    d->errbuf[0] = '\0';
    d->easy = curl_easy_init();
    struct curl_slist *h = curl_slist_append(NULL, "Content-Type: application/json");
    struct curl_slist *h2 = h ? curl_slist_append(h, attempt_header) : NULL;
    d->headers = h2 ? curl_slist_append(h2, "Expect:") : NULL;
    if (!d->easy || !d->headers) {
        snprintf(err, err_size, "%s", d->easy ? "out of memory" : "cannot create a libcurl handle");
        curl_slist_free_all(d->headers ? d->headers : h2 ? h2 : h);
        curl_easy_cleanup(d->easy);
        d->easy = NULL, d->headers = NULL;
        return false;
    }
    CURL *c = d->easy;
    curl_easy_setopt(c, CURLOPT_URL, d->url);
    curl_easy_setopt(c, CURLOPT_PROTOCOLS_STR, "http,https");
    curl_easy_setopt(c, CURLOPT_FOLLOWLOCATION, 0L);
    curl_easy_setopt(c, CURLOPT_NOSIGNAL, 1L);
    curl_easy_setopt(c, CURLOPT_CONNECTTIMEOUT, 5L);
    curl_easy_setopt(c, CURLOPT_TIMEOUT, (long)NOTIFY_TIMEOUT_S);
    curl_easy_setopt(c, CURLOPT_USERAGENT, agent);
    curl_easy_setopt(c, CURLOPT_HTTPHEADER, d->headers);
    curl_easy_setopt(c, CURLOPT_POSTFIELDS, d->body);
    curl_easy_setopt(c, CURLOPT_POSTFIELDSIZE, (long)strlen(d->body));
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, discard);
    curl_easy_setopt(c, CURLOPT_ERRORBUFFER, d->errbuf);
    curl_easy_setopt(c, CURLOPT_PRIVATE, d);
    if (curl_multi_add_handle(n->multi, c) != CURLM_OK) {
        snprintf(err, err_size, "cannot start the request");
        curl_slist_free_all(d->headers);
        curl_easy_cleanup(c);
        d->easy = NULL, d->headers = NULL;
        return false;
    }
    n->in_flight++;
    return true;
}

/* An attempt ended, with HTTP status (0: no answer, why in err): d is
 * delivered, given up, or queued again after 1, 2, 4, 8, 16 s. */
static void attempt_end(mr_notifier *n, delivery *d, long status, const char *err)
{
    d->attempts++;
    const bool ok = status >= 200 && status < 300;
    char why[CURL_ERROR_SIZE + 32];
    if (!ok && status)
        snprintf(why, sizeof why, "answered %ld", status);
    else
        snprintf(why, sizeof why, "%s", err);
    if (ok) {
        if (d->attempts > 1)
            say(n, "notify %s: delivered at attempt %d", d->url, d->attempts);
        delivery_free(d);
    } else if (d->attempts >= NOTIFY_ATTEMPTS) {
        say(n, "notify %s: given up after %d attempts (%s)", d->url, d->attempts, why);
        delivery_free(d);
    } else {
        d->due = mr_now() + (double)(1 << (d->attempts - 1));
        pthread_mutex_lock(&n->mu);
        enqueue(n, d);
        pthread_mutex_unlock(&n->mu);
    }
}

/* The attempts in flight that ended: their answers handed to attempt_end. */
static void collect(mr_notifier *n)
{
    CURLMsg *m;
    int left;
    while ((m = curl_multi_info_read(n->multi, &left)) != NULL) {
        if (m->msg != CURLMSG_DONE)
            continue;
        CURL *c = m->easy_handle;
        const CURLcode rc = m->data.result;
        delivery *d = NULL;
        curl_easy_getinfo(c, CURLINFO_PRIVATE, (char **)&d);
        long status = 0;
        if (rc == CURLE_OK)
            curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &status);
        char err[CURL_ERROR_SIZE];
        snprintf(err, sizeof err, "%s", d->errbuf[0] ? d->errbuf : curl_easy_strerror(rc));
        curl_multi_remove_handle(n->multi, c);
        curl_easy_cleanup(c);
        curl_slist_free_all(d->headers);
        d->easy = NULL, d->headers = NULL;
        n->in_flight--;
        attempt_end(n, d, status, err);
    }
}

static void *notifier_main(void *arg)
{
    mr_notifier *n = arg;
    for (;;) {
        /* the deliveries now due go in flight (not once stopping: a stop
         * waits for the attempts in flight and drops the rest) */
        pthread_mutex_lock(&n->mu);
        const bool stop = n->stop;
        double now = mr_now();
        while (!stop && n->queue && n->queue->due <= now && n->in_flight < NOTIFY_IN_FLIGHT) {
            delivery *d = n->queue;
            n->queue = d->next;
            pthread_mutex_unlock(&n->mu);
            char err[64];
            if (!attempt_start(n, d, err, sizeof err))
                attempt_end(n, d, 0, err);
            pthread_mutex_lock(&n->mu);
        }
        const double next = n->queue ? n->queue->due : INFINITY;
        pthread_mutex_unlock(&n->mu);
        if (stop && n->in_flight == 0)
            break;
        int running = 0;
        curl_multi_perform(n->multi, &running);
        collect(n);
        /* until a transfer moves, a delivery falls due, or send or stop
         * wakes the thread (at most a second: a clock step is no stall) */
        double wait = n->in_flight ? 1.0 : fmin(1.0, fmax(0.0, next - mr_now()));
        if (stop || (n->in_flight < NOTIFY_IN_FLIGHT && next <= mr_now()))
            wait = n->in_flight ? 0.05 : 0.0;
        curl_multi_poll(n->multi, NULL, 0, (int)(wait * 1000), NULL);
    }
    size_t dropped = 0;
    pthread_mutex_lock(&n->mu);
    for (delivery *d = n->queue, *next; d; d = next) {
        next = d->next;
        delivery_free(d);
        dropped++;
    }
    n->queue = NULL;
    pthread_mutex_unlock(&n->mu);
    if (dropped)
        say(n, "notify: %zu pending deliver%s dropped at stop", dropped, dropped == 1 ? "y" : "ies");
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
    if (!(n->multi = curl_multi_init())) {
        free(n);
        return mr_error_set(err, MR_ERR_NOMEM, "cannot create the notifications' libcurl handle");
    }
    if (pthread_mutex_init(&n->mu, NULL) != 0 || pthread_create(&n->thread, NULL, notifier_main, n) != 0) {
        curl_multi_cleanup(n->multi);
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
    pthread_mutex_unlock(&n->mu);
    curl_multi_wakeup(n->multi);
}

void mr_notifier_stop(mr_notifier *n)
{
    if (!n)
        return;
    pthread_mutex_lock(&n->mu);
    n->stop = true;
    pthread_mutex_unlock(&n->mu);
    curl_multi_wakeup(n->multi);
    pthread_join(n->thread, NULL);
    curl_multi_cleanup(n->multi);
    pthread_mutex_destroy(&n->mu);
    free(n);
}
